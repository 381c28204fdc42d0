"""The plot of `main.py detect`: each test trajectory's residual/threshold ratio per joint, detections and pushes."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")  # files only: the command runs headless
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

if TYPE_CHECKING:
    from tasks.lab.detect import PlotRun


def plot_detections(runs: list[PlotRun], path: Path, title: str) -> Path:
    """One panel per trajectory: |r_j| / thr_j per joint over time (1 = the threshold), detections as
    vertical lines, pushes (held poses) shaded from onset to end."""
    n = max(len(runs), 1)
    fig, axes = plt.subplots(n, 1, figsize=(11, 1.9 * n + 0.8), squeeze=False)
    colours = plt.get_cmap("tab10")
    for ax, (name, run, pushes) in zip(axes[:, 0], runs, strict=False):
        for j in range(run.ratio.shape[1]):
            ax.plot(run.t_s, run.ratio[:, j], lw=0.8, color=colours(j), label=f"J{j + 1}")
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        for p in pushes:
            ax.axvspan(p["onset_s"], p["end_s"], color="0.85", lw=0)
        for d in run.detections:
            ax.axvline(d["t_s"], color="red", lw=1.0)
            ax.annotate(f"J{d['joint']}", (d["t_s"], 1.0), xytext=(2, 4), textcoords="offset points",
                        color="red", fontsize=7)
        peak = float(np.nanmax(run.ratio)) if np.isfinite(run.ratio).any() else 1.0
        ax.set_ylim(0, max(1.3, min(peak * 1.1, 6.0)))
        ax.set_xlim(0, float(run.t_s[-1]) if len(run.t_s) else 1.0)
        ax.set_ylabel("|r| / thr", fontsize=8)
        ax.set_title(f"{name}: {len(run.detections)} detection(s), max free ratio {run.max_free_ratio:.2f}",
                     fontsize=9, loc="left")
        ax.tick_params(labelsize=7)
    axes[0, 0].legend(ncol=6, fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("s from the trajectory's first sample")
    fig.suptitle(f"{title}\nred: detections; grey: pushes (torque > 15 N·m from rest >= 0.1 s)", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
