"""The model lab's evaluation report: the Markdown table and the plot of `evaluate`'s summary."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def evaluation_table(summary: dict[str, Any]) -> str:
    """The per-model RMSE table (Markdown) written as `table.md`."""
    lines = ["# Torque RMSE on held-out test trajectories (N·m)", "",
             f"{summary['test_trajectories']} test trajectories, {summary['train_samples']} training samples "
             f"({summary['large_samples']} for D_large); torque-noise floor joints 1-3: "
             f"{summary['noise_floor_j123_nm']}", "",
             "| model | samples | mean J1-3 | std | max | min | mean J1 | J2 | J3 | J4 | J5 | J6 | nMSE J1-3 |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in summary["models"].items():
        j = r["j123"]
        per = ["-" if v is None else f"{v:.3f}" for v in r["rmse_mean"]]
        nm = [v for v in r["nmse_mean"][:3] if v is not None]
        lines.append(f"| {name} | {r['training_samples']} | {j['mean']:.3f} | {j['std']:.3f} | {j['max']:.3f} | "
                     f"{j['min']:.3f} | " + " | ".join(per) + f" | {np.mean(nm):.4f} |")
    lines += ["", f"p2_over_p1 = {summary['p2_over_p1']:.3f}, h1_over_p2 = {summary['h1_over_p2']:.3f}, "
              f"h1_is_best = {summary['h1_is_best']}", ""]
    return "\n".join(lines)


def plot_evaluation(summary: dict[str, Any], path: Path) -> Path:
    """Per-joint RMSE bars per model and the learning curves, saved to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 5))
    names = list(summary["models"])
    n_j = len(summary["models"][names[0]]["rmse_mean"])
    width = 0.8 / len(names)
    for i, name in enumerate(names):
        vals = [np.nan if v is None else v for v in summary["models"][name]["rmse_mean"]]
        errs = [np.nan if v is None else v for v in summary["models"][name]["rmse_std"]]
        ax.bar(np.arange(n_j) + i * width, vals, width, yerr=errs, label=name, capsize=2)
    if summary.get("noise_floor_per_joint_nm"):
        for j, v in enumerate(summary["noise_floor_per_joint_nm"]):
            ax.plot([j - 0.1, j + 0.9], [v, v], "k--", lw=1, label="noise floor" if j == 0 else None)
    ax.set_xticks(np.arange(n_j) + 0.4, [f"J{j + 1}" for j in range(n_j)])
    ax.set_ylabel("per-trajectory RMSE [N·m] (mean ± std)")
    ax.set_yscale("log")
    ax.set_title("torque error on held-out test trajectories")
    ax.legend(fontsize=8, ncol=2)
    ax.grid(alpha=0.3, axis="y")
    for kind, pts in summary["learning_curve"].items():
        if pts:
            ax2.plot([p["samples"] for p in pts], [p["rmse_j123"] for p in pts], "o-", label=kind)
    for name, style in (("P1", ":"), ("P2", "--")):
        v = summary["mean_rmse_j123"][name]
        ax2.axhline(v, ls=style, color="gray", label=f"{name} ({v:.2f})")
    if summary.get("noise_floor_j123_nm"):
        ax2.axhline(summary["noise_floor_j123_nm"], ls="-.", color="k", lw=0.8, label="noise floor")
    ax2.set_xscale("log")
    ax2.set_xlabel("training samples")
    ax2.set_ylabel("mean RMSE joints 1-3 [N·m]")
    ax2.set_title("learning curves")
    ax2.legend()
    ax2.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
