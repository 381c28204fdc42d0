"""Force primitives (move, guarded_move, force_mode, spiral_search, hold, wait, tare, report) and the task
files that sequence them (docs/task-files.md)."""
