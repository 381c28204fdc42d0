"""The model lab's data collection: training and test motion played on a cell, written as a dataset.

`collect` takes an `open_cell_fn` returning an object with `.open() -> OpenCell` and `.close()` (so tasks/
never imports sim/).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import yaml
from tqdm import tqdm

from cell.config import CellConfig
from cell.control.loop import ControlLoop
from cell.control.safety import SafetyMonitor
from cell.control.signals import raise_if_interrupted
from cell.data.excitation.chain import paper_chain
from cell.data.excitation.config import ExcitationConfig, read_excitation_config
from cell.data.excitation.fast import fast_moves
from cell.data.excitation.fourier import fourier_excitation
from cell.data.excitation.motion import Motion, Segment
from cell.data.excitation.moves import join_motions, random_moves, transfer
from cell.data.excitation.sweep import sweep_excitation
from cell.data.outputs import check_out_dir
from cell.data.recorder import Recorder, new_run_dir, read_log
from cell.model.robot import RobotModel
from cell.model.specs import CELL_ROBOT, robot_by_name
from cell.planning.config import PlannerConfig
from drivers.configio import to_plain
from drivers.errors import ConfigError, DataError
from tasks.lab.playback import PlaybackTask

log = logging.getLogger(__name__)


def collect(
    cfg: CellConfig,
    open_cell_fn: Callable[[], Any],
    out_dir: Path,
    samples: int = 500_000,
    family: str = "mixed",
    fourier_share: float = 0.7,
    test_trajectories: int = 6,
    test_repeats: int = 5,
    test_moves: int = 4,
    excitation: str | None = None,
    seed: int = 0,
    slow_share: float = 0.0,
    sweep_share: float = 0.0,
    sweep_centre: np.ndarray | None = None,
    robot: str = CELL_ROBOT,
    fast_share: float = 0.0,
    fast_planner: PlannerConfig | None = None,
) -> dict[str, Any]:
    """Run training and test trajectories on a cell through the control loop (safety, recording) and
    write a dataset: `<out>/train.parquet`, `<out>/test.parquet`, `<out>/dataset.yaml`, `<out>/collect.json`.

    Training family: `paper` (the digitised-configuration chain at V speeds), `fourier`
    (identification-grade excitation) or `mixed` (`fourier_share` of the samples Fourier excitation
    including the moves to each excitation's start, the rest chain: the chain alone visits poses
    along a few straight lines in joint space, too few for a purely learned model to generalise).  Test family:
    random point-to-point moves in the test ranges, `test_trajectories` x `test_repeats`.

    CLI: main.py collect --cell sim --out artifacts/data/default --samples 500000
         [--family mixed|paper|fourier] [--fourier-share 0.7]
         [--test-trajectories 6] [--test-repeats 5] [--test-moves 4]
         [--excitation config/excitation.yaml] [--plant config/plants/alt.yaml] [--seed 0] [--json]
    """
    if robot != CELL_ROBOT:
        raise ConfigError(f"collect --robot {robot}: the simulated plant is a {CELL_ROBOT}; "
                          f"import another robot's logs instead (main.py import ur10e)")
    out_dir = check_out_dir(Path(out_dir))  # before the motion: a dataset that cannot be written is lost
    out_dir.mkdir(parents=True, exist_ok=True)
    robot_model = robot_by_name(cfg)
    ex = read_excitation_config(str(excitation) if excitation else None)  # a CLI path: relative to the cwd
    ex = dataclasses.replace(ex, seed=ex.seed + seed)
    dt = cfg.loop.period_s
    t0 = time.perf_counter()
    train_plan = training_plan(robot_model, cfg, ex, dt, samples, family, fourier_share, slow_share, sweep_share,
                               sweep_centre, fast_share, fast_planner)
    plans: list[tuple[str, Motion]] = [("train", train_plan)]
    if test_trajectories > 0:
        test_plan = random_moves(robot_model, cfg, ex, dt, test_trajectories, test_moves, list(ex.speeds),
                                 repeats=test_repeats, seed=ex.seed + 1000)
        plans.append(("test", test_plan))
    log.info("planned %s in %.1f s", ", ".join(f"{k}: {p.samples} samples" for k, p in plans),
             time.perf_counter() - t0)
    # Moves between the plans are planned now, so a blocked transfer fails before any motion.
    for k in range(1, len(plans)):
        lead = transfer(plans[k - 1][1].segments[-1].q[-1], plans[k][1].start, robot_model, cfg, ex, dt)
        plans[k] = (plans[k][0], Motion(lead + plans[k][1].segments, dt, plans[k][1].info))
    rec_cfg = dataclasses.replace(cfg, recording=dataclasses.replace(
        cfg.recording, directory=str(out_dir / "runs"), chunk_rows=max(cfg.recording.chunk_rows, 5000)))
    split_cfg = {"train": rec_cfg, "test": rec_cfg}
    if fast_share > 0 and fast_planner is not None:
        # The fast moves run at `plan`'s TCP speeds, under its stop; every other part was planned under the
        # cell's own limit, which still bounds them.
        split_cfg["train"] = dataclasses.replace(rec_cfg, safety=dataclasses.replace(
            cfg.safety, max_tcp_speed=max(cfg.safety.max_tcp_speed, fast_planner.tcp_speed_limit)))
    results: dict[str, Any] = {}
    holder = open_cell_fn()
    cell = holder.open()
    try:
        for i, (split, plan) in enumerate(plans):
            if i == 0:
                lead = transfer(cell.arm.read_state().q, plan.start, robot_model, cfg, ex, dt)
                plan = Motion(lead + plan.segments, dt, plan.info)
            res = _play(plan, split, cell, split_cfg[split], robot_model)
            results[split] = res
            raise_if_interrupted(res["outcome"])
            if res["outcome"] != "done":
                raise DataError(f"collect {split}: the run ended '{res['outcome']}' ({res['reason']}); "
                                f"recording kept in {res['run_dir']}")
            table = _dataset_table(Path(res["run_dir"]), robot_model.n)
            pq.write_table(table, out_dir / f"{split}.parquet")
            res["rows"] = table.num_rows
    finally:
        holder.close()
    manifest = {
        "description": f"{family} training family, random point-to-point test family; cell {cfg.source or 'default'}",
        "robot": robot_model.model.name, "joints": robot_model.n, "period_s": dt,
        "train": ["train.parquet"], "test": ["test.parquet"] if "test" in results else [],
    }
    (out_dir / "dataset.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    summary = {
        "out_dir": str(out_dir), "manifest": str(out_dir / "dataset.yaml"), "plant": cfg.plant, "family": family,
        "train_samples": results["train"]["rows"], "test_samples": results.get("test", {}).get("rows", 0),
        "plans": {k: to_plain(p.info) for k, p in plans}, "runs": results,
        "wall_s": time.perf_counter() - t0,
    }
    (out_dir / "collect.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


SLOW_SPEED_FRACTION = 0.02  # slow excitation: joint speeds up to 2 % of the limits (~0.05 rad/s)


def training_plan(robot: RobotModel, cfg: CellConfig, ex: ExcitationConfig, dt: float, samples: int,
                  family: str, fourier_share: float = 0.7, slow_share: float = 0.0, sweep_share: float = 0.0,
                  sweep_centre: np.ndarray | None = None, fast_share: float = 0.0,
                  fast_planner: PlannerConfig | None = None) -> Motion:
    """The training motion.  `slow_share` > 0 (what `prepare` collects) adds about `slow_share * samples`
    samples of slow, small-amplitude Fourier excitation around random centres to the family's
    `samples`: the joint speeds of careful task motion (0.005-0.05 rad/s), where the friction is in
    its Stribeck regime and the fast families only pass through at their turning points.
    `sweep_share` > 0 adds about `sweep_share * samples` samples of slow constant-speed sweeps around
    `sweep_centre`, the tool's working posture (`cell.data.excitation.sweep.sweep_excitation`).
    `fast_share` > 0 adds about `fast_share * samples` samples of moves timed as `plan` times them
    (`fast_planner`'s limits; `cell.data.excitation.fast.fast_moves`): the cell's working speeds."""
    if not 0 < fourier_share < 1:
        raise ConfigError(f"--fourier-share {fourier_share}: must lie in (0, 1)")
    if fast_share > 0:
        if not fast_share < 1:
            raise ConfigError(f"fast_share {fast_share}: must lie in [0, 1)")
        if fast_planner is None or fast_planner.tcp_speed_limit <= 0:
            raise ConfigError("fast_share > 0 needs the planner settings `plan` runs under, with a TCP speed limit")
        planner = fast_planner  # (a local the lambda below sees as checked)
        base = training_plan(robot, cfg, ex, dt, samples, family, fourier_share, slow_share, sweep_share,
                             sweep_centre)
        return _appended(base, "fast", fast_share, "fast moves", lambda start, seg: fast_moves(
            robot, cfg, ex, dt, int(samples * fast_share), planner, start=start, traj_base=900, segment_base=seg))
    if not 0 <= slow_share < 1:
        raise ConfigError(f"slow_share {slow_share}: must lie in [0, 1)")
    if sweep_share > 0:
        if sweep_centre is None:
            raise ConfigError("sweep_share > 0 needs the working posture to sweep around")
        centre = sweep_centre  # (a local the lambda below sees as checked)
        base = training_plan(robot, cfg, ex, dt, samples, family, fourier_share, slow_share)
        return _appended(base, "sweep", sweep_share, "slow sweeps around the working posture",
                         lambda start, seg: sweep_excitation(robot, cfg, ex, dt, int(samples * sweep_share), centre,
                                                             start=start, traj_base=700, segment_base=seg))
    if slow_share > 0:
        slow_n = int(samples * slow_share)
        fast = training_plan(robot, cfg, ex, dt, samples, family, fourier_share)
        # Few candidates: the slow part is for the friction, not for the rigid-body identification.
        fc = dataclasses.replace(ex.fourier, ramp_s=1.0, candidates=3)
        per_traj = (fc.periods / fc.base_hz + 2 * fc.ramp_s) / dt
        k = max(1, int(np.ceil(slow_n / per_traj)))
        slow = fourier_excitation(robot, cfg, dataclasses.replace(
            ex, seed=ex.seed + 500, fourier=dataclasses.replace(fc, trajectories=k)), dt, traj_base=300,
            segment_base=max(s.segment for s in fast.segments) + 1, speed_fraction=SLOW_SPEED_FRACTION)
        joined = join_motions([fast, slow], robot, cfg, ex)
        return Motion(joined.segments, dt, {**joined.info, "slow": slow.info, "slow_share": slow_share})
    if family == "paper":
        return paper_chain(robot, cfg, ex, dt, max_samples=samples)
    if family in ("fourier", "mixed"):
        share = samples if family == "fourier" else int(samples * fourier_share)
        per_traj = (ex.fourier.periods / ex.fourier.base_hz + 2 * ex.fourier.ramp_s) / dt
        k = max(1, int(np.ceil(share / per_traj)))
        four = fourier_excitation(robot, cfg, dataclasses.replace(ex, fourier=dataclasses.replace(
            ex.fourier, trajectories=k)), dt, traj_base=100)
        # The moves to each excitation's start are data too: keep whole trajectories up to the share.
        kept: list[Segment] = []
        for tid in sorted({seg.traj for seg in four.segments}):
            if sum(len(seg.q) for seg in kept) >= share:
                break
            kept += [seg for seg in four.segments if seg.traj == tid]
        four = Motion(kept, dt, {**four.info, "trajectories": len({seg.traj for seg in kept})})
        if family == "fourier":
            return four
        chain = paper_chain(robot, cfg, ex, dt, max_samples=max(1, samples - four.labelled_samples),
                            segment_base=max(s.segment for s in four.segments) + 1)
        return join_motions([chain, four], robot, cfg, ex)
    raise ConfigError(f"--family {family}: unknown (paper, fourier, mixed)")


def _appended(base: Motion, key: str, share: float, what: str,
              make: Callable[[np.ndarray, int], Motion]) -> Motion:
    """`base` followed by the part `make(start, segment_base)` makes from where `base` ends (its segment ids
    after base's), its info under `key`; a part that cannot be made is a ConfigError naming `what`."""
    try:
        part = make(base.segments[-1].q[-1], max(s.segment for s in base.segments) + 1)
    except ValueError as exc:
        raise ConfigError(f"{what}: {exc}") from None
    return Motion(base.segments + part.segments, base.dt, {**base.info, key: part.info, f"{key}_share": share})


def _play(plan: Motion, split: str, cell: Any, cfg: CellConfig, robot: RobotModel) -> dict[str, Any]:
    """One plan through the control loop with safety and recording (no force plot: these runs are long)."""
    run_dir = new_run_dir(Path(cfg.recording.directory), f"collect-{split}")
    recorder = Recorder(run_dir, cfg.recording.chunk_rows)
    recorder.write_config(to_plain(cfg))
    with tqdm(total=plan.samples, desc=f"collect {split}", unit="sample", smoothing=0.05) as bar:
        task = PlaybackTask(plan, robot, cfg.loop.period_s, progress=bar.update)
        max_s = plan.duration_s + 120.0
        loop = ControlLoop(cell.arm, cell.force, task, SafetyMonitor(cfg.safety, robot, cfg.loop.period_s),
                           cell.ticker, recorder, cfg.loop.period_s, max_s, cfg.loop.slow_cycle_fraction,
                           ground_truth=cell.ground_truth)
        result = loop.run()
    summary = dict(task.summary())
    if result.outcome != "done":
        summary["outcome"] = result.outcome
        summary["reason"] = summary.get("reason") or result.reason
    summary.update(run_dir=str(run_dir), cycles=result.cycles, sim_time_s=result.sim_time_s,
                   wall_time_s=result.wall_time_s,
                   real_time_factor=result.sim_time_s / result.wall_time_s if result.wall_time_s else None)
    recorder.write_summary(summary)
    return summary


def _dataset_table(run_dir: Path, n: int) -> pa.Table:
    """The dataset columns of a run's step log, rows that belong to a trajectory only."""
    log_table = read_log(run_dir)
    keep = pc.greater_equal(log_table.column("traj"), 0)
    t = log_table.filter(keep)
    cols = ["t"] + [f"{p}{i}" for p in ("q", "dq", "tau") for i in range(1, n + 1)]
    out = t.select(cols)
    out = out.append_column("traj", pc.cast(t.column("traj"), pa.int64()))
    return out.append_column("segment", pc.cast(t.column("segment"), pa.int64()))
