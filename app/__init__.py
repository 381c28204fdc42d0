"""The composition layer: each command's parser and body, assembling tasks, benches and cells.

Command bodies import what they run inside the body (the simulator, the models, the benches): those pull in
MuJoCo, Pinocchio, XGBoost and JAX, which `main.py --help` or `status` must not wait for.
"""
