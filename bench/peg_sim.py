"""How far the simulator holds at tight peg fits: the collider's bore, contact yield, wedging vs geometry, cost.

Run: `main.py bench peg-sim [--json]` (or `python -m bench.peg_sim`) -> artifacts/bench/peg-sim.json and
artifacts/bench/peg-sim.png
(docs/peg.md has the numbers)."""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from cell.config import load_config, resolve
from sim import mjcf
from sim.peg_fit import Fit, bore_error, predicted_jam_depth, wedge
from sim.plant import Plant
from sim.profile import load_profile

log = logging.getLogger(__name__)

CLEARANCES_MM = (0.4, 0.1, 0.05)  # diametral, in the 21.8 mm bore: the paper's, and the two tight fits
TILTS_DEG = (0.5, 1.0, 2.0, 4.0)
PUSHES_N = (15.0, 40.0, 80.0)  # the task's insertion push, and above it up to its force limit
SOLIMPS = {"plant (0.95)": mjcf.FIT_SOLIMP, "stiffer (0.99)": "0.99 0.995 0.0002"}


def measure() -> dict[str, Any]:
    """Every rig measurement behind the figure (about a minute)."""
    out: dict[str, Any] = {"segments": mjcf.HOLE_WALL_SEGMENTS, "solref": mjcf.FIT_SOLREF, "bore": [], "wedge": []}
    for c_mm in CLEARANCES_MM:
        fit = Fit(peg_d=0.0218 - c_mm * 1e-3)
        for segments in (16, 32, 64):
            out["bore"].append({"clearance_mm": c_mm, "segments": segments,
                                "bore_error_um": round(bore_error(fit, segments=segments) * 1e6, 3)})
    for label, solimp in SOLIMPS.items():
        for c_mm in CLEARANCES_MM:
            fit = Fit(peg_d=0.0218 - c_mm * 1e-3)
            for tilt in TILTS_DEG:
                if predicted_jam_depth(fit, math.radians(tilt)) > 0.028:
                    continue  # would not wedge inside the 30 mm bore
                for push in PUSHES_N:
                    w = wedge(fit, tilt, push_n=push, side_n=push / 5, solimp=solimp)
                    out["wedge"].append({
                        "contact": label, "clearance_mm": c_mm, "tilt_deg": tilt, "push_n": push,
                        "predicted_mm": round(w.predicted_depth_m * 1e3, 3), "depth_mm": round(w.depth_m * 1e3, 3),
                        "penetration_um": round(w.max_penetration_m * 1e6, 2),
                        "max_contact_n": round(w.max_contact_force_n, 1),
                        "wall_s_per_sim_s": round(w.wall_s_per_sim_s, 3)})
    # The time step: half the plant's, with the contact's time constant halved with it (MuJoCo's floor is 2 steps)
    out["half_step"] = []
    for c_mm in CLEARANCES_MM[1:]:
        fit = Fit(peg_d=0.0218 - c_mm * 1e-3)
        for push in PUSHES_N:
            for dt in (0.001, 0.0005):
                w = wedge(fit, 1.0, push_n=push, side_n=push / 5, dt=dt)
                out["half_step"].append({"clearance_mm": c_mm, "push_n": push, "dt_ms": dt * 1e3,
                                         "predicted_mm": round(w.predicted_depth_m * 1e3, 3),
                                         "depth_mm": round(w.depth_m * 1e3, 3),
                                         "penetration_um": round(w.max_penetration_m * 1e6, 2)})
    out["plant_cost"] = plant_cost()
    return out


def plant_cost(periods: int = 250) -> list[dict[str, Any]]:
    """Wall time per simulated second of the whole plant (arm, servo, peg scene) holding still, per physics step."""
    cfg = load_config(None)
    profile = load_profile(resolve(cfg.plant))
    scene = replace(cfg.scene, kind="peg")
    q0 = np.asarray(cfg.robot.home, float)
    rows = []
    for dt in (0.001, 0.0005):
        plant = Plant(resolve(cfg.robot.urdf), profile, scene, q0, physics_dt=dt)
        t0 = time.perf_counter()
        for _ in range(periods):
            plant.set_target(q0)
            plant.step()
        rows.append({"physics_dt_ms": dt * 1e3,
                     "wall_s_per_sim_s": round((time.perf_counter() - t0) / (periods * plant.dt), 3)})
    return rows


def plot(data: dict[str, Any], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2))
    plant = [w for w in data["wedge"] if w["contact"] == "plant (0.95)"]
    for c_mm, colour in zip(CLEARANCES_MM, ("tab:green", "tab:blue", "tab:red"), strict=True):
        rows = [w for w in plant if w["clearance_mm"] == c_mm and w["push_n"] == 15.0]
        if rows:
            a1.plot([w["tilt_deg"] for w in rows], [w["predicted_mm"] for w in rows], "-", color=colour,
                    label=f"{c_mm} mm: geometry")
            a1.plot([w["tilt_deg"] for w in rows], [w["depth_mm"] for w in rows], "o", color=colour,
                    label=f"{c_mm} mm: simulated (15 N)")
        for push, marker in zip(PUSHES_N, ("o", "s", "^"), strict=True):
            pts = [w for w in plant if w["clearance_mm"] == c_mm and w["push_n"] == push]
            a2.plot([w["tilt_deg"] for w in pts], [w["penetration_um"] for w in pts], marker, color=colour,
                    label=f"{c_mm} mm, {push:.0f} N")
        if c_mm < 0.4:
            a2.axhline(c_mm * 100, color=colour, ls="--", lw=0.8)  # a tenth of the clearance [um]
    a1.set(xlabel="peg tilt [deg]", ylabel="wedged at depth [mm]", yscale="log",
           title="Where a tilted peg wedges: clearance / tan(tilt)")
    a2.set(xlabel="peg tilt [deg]", ylabel="deepest contact [um]",
           title="Contact penetration (dashed: a tenth of each fit)")
    a1.legend(fontsize=7)
    a2.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    data = measure()
    out = Path("artifacts/bench")
    out.mkdir(parents=True, exist_ok=True)
    (out / "peg-sim.json").write_text(json.dumps(data, indent=1))
    log.info("peg-sim: %s", plot(data, out / "peg-sim.png"))


if __name__ == "__main__":
    main()
