"""`main.py bench planning`: its options and its assembly (model, paths, plant runs) for bench/planning.py."""

from __future__ import annotations

import argparse
import logging
from dataclasses import replace
from typing import Any

import numpy as np

from app.cells import cell_identity, open_cell
from app.common import load_cell_config
from app.planning_model import ARTEFACTS, PLANS, planning_model
from app.sensing import with_guard
from cell.cliargs import int_in
from drivers.errors import ConfigError

log = logging.getLogger("tmcell")
PLANNING_PATHS = 20
PPO_UPDATES = 300  # PPO rollouts of 32 paths: about a minute on one core (docs/planning.md)


def add_planning_options(b: argparse.ArgumentParser) -> None:
    """The options of `bench planning` (app/commands_bench.py adds them to its parser)."""
    b.add_argument("--paths", type=int_in(1, 500), default=PLANNING_PATHS,
                   help="random collision-free paths besides the three named ones")
    b.add_argument("--ppo-updates", type=int_in(1, 10_000), default=PPO_UPDATES,
                   help="PPO training updates (rollouts of 32 paths) when the stored policy is missing or differs")
    b.add_argument("--paths-class", choices=("speed", "torque", "mixed"), default="speed",
                   help="the random paths: across the workspace (speed-bound), short and medium joint 1-3 moves "
                        "(torque-bound), or both alternately")
    b.add_argument("--no-guard", action="store_true",
                   help="run the plans without the collision guard (torques only; docs/planning.md)")


def planning_tags(args: argparse.Namespace) -> list[str]:
    tags = [f"{args.paths}paths"] if args.paths != PLANNING_PATHS else []
    if args.ppo_updates != PPO_UPDATES:
        tags.append(f"ppo{args.ppo_updates}")
    if args.paths_class != "speed":
        tags.append(args.paths_class)
    return tags + (["noguard"] if args.no_guard else [])


def bench_planning_cmd(args: argparse.Namespace) -> dict[str, Any]:
    """Assemble the bench: the prepared hybrid model, config/plans.yaml's planner settings and named paths,
    and the simulated cell (guarded unless --no-guard) to execute each plan on."""
    from bench.planning import PlanningSetup, bench_planning
    from bench.planning_calibration import CALIBRATION_SEED
    from cell.collision.geometry import CollisionChecker
    from cell.planning.planner import TimedTrajectory
    from cell.planning.ppo_planner import PpoSettings
    from tasks.setup.plan import execute, load_plan_file, measured_peak

    cfg = load_cell_config(args)
    plan_file = load_plan_file(PLANS)
    robot, predictor, model_name, terms = planning_model(cfg, args.model, "sim", plan_file.max_tcp_speed)
    effort = robot.limits.effort
    if not np.all(np.isfinite(effort) & (effort > 0)):
        raise ConfigError("bench planning: the robot's URDF has no finite effort limits")

    def runner(guarded: bool, seed: int | None) -> Any:
        def open_for_plan() -> tuple[Any, Any]:
            holder = open_cell(cfg, "sim", robot, seed, "free")
            try:
                cell = holder.open()
                return (with_guard(cfg, "wipe", cell, robot) if guarded else cell), holder
            except BaseException:
                holder.close()
                raise

        def run(traj: TimedTrajectory) -> dict[str, Any]:
            summary = execute(traj, cfg, robot, open_for_plan)
            peak = measured_peak(summary.get("run_dir"), robot.n)
            return {**summary, "peak_ratio": peak / effort}

        return run

    identity = {k: v for k, v in cell_identity(cfg, "sim", args.seed).items() if k != "seed"}  # noise only
    settings = PpoSettings()
    settings.ppo.updates = args.ppo_updates
    setup = PlanningSetup(
        robot=robot, torque_fn=predictor, terms=terms, model_name=model_name, pcfg=plan_file.planner,
        named=plan_file.paths, collisions=CollisionChecker.for_scene(robot, replace(cfg.scene, kind="free")),
        run=runner(not args.no_guard, args.seed),
        # The calibration measures torques only: the guard cannot change them, and a false detection would
        # cut a reference run short and bias the accelerations low (docs/planning.md).  Its runs have their own
        # noise seed, so the stored settings do not depend on the bench seed that happened to make them.
        calibration_run=runner(False, CALIBRATION_SEED),
        safety_fraction=cfg.safety.joint_torque_fraction,
        workspace=(np.asarray(cfg.safety.workspace_min, float), np.asarray(cfg.safety.workspace_max, float)),
        artefacts=ARTEFACTS, arm_identity=identity,
    )
    out = bench_planning(setup, args.paths, args.seed if args.seed is not None else 0, settings, args.paths_class)
    out["guarded"] = not args.no_guard
    return out
