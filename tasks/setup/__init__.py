"""Setting a cell up and checking it: calibrate the virtual sensor, weigh the tool, doctor the wiring,
replay a run, plan and play time-optimal motions."""
