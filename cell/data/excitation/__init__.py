"""Motion generators for data collection: the paper's digitised-configuration chain, Fourier excitation,
slow sweeps, random moves.

All of them return a `Motion` (motion.py): joint-position samples at the control period, cut into segments
(moves) and trajectories, that avoid self-collision and the cell's fixtures (Pinocchio geometry / Coal on
the URDF's collision boxes plus the tool, the table and the floor), keep the TCP inside the safety
workspace, and respect joint speed, joint acceleration and commanded TCP speed limits (limits.py).
Generators: chain.py (the paper's), fourier.py, sweep.py, and moves.py (quintic moves, transfers, random
moves); their settings in config.py.
"""
