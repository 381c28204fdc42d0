"""Time-efficient trajectories: the time-optimal planner on the torque model, and the paper's PPO
path-speed planner with its environment."""
