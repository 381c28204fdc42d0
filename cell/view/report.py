"""Plots of a recorded run (PNG): the normal force against its setpoint, like the paper's Fig. 12; the limits
drawn (or named at the edge when far off the scale) and the F/T sensor's peak after the tare marked."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")  # files only: the cell runs headless
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pyarrow as pa  # noqa: E402


def _state_spans(t: np.ndarray, states: list[str]) -> list[tuple[float, float, str]]:
    spans, start = [], 0
    for i in range(1, len(states) + 1):
        if i == len(states) or states[i] != states[start]:
            spans.append((float(t[start]), float(t[i - 1]), states[start]))
            start = i
    return spans


def _shade_states(fig: plt.Figure, axes: list, t: np.ndarray, states: list[str]) -> None:
    """Shade each state's span on `axes`; one legend of the states above them all (so none covers data)."""
    palette = plt.get_cmap("tab20")  # 20 colours: a task's states never share one
    names = list(dict.fromkeys(states))
    for ax in axes:
        for t0, t1, s in _state_spans(t, states):
            ax.axvspan(t0, t1, color=palette(names.index(s) % 20), alpha=0.22, lw=0)
    handles = [plt.Rectangle((0, 0), 1, 1, color=palette(i % 20), alpha=0.22) for i in range(len(names))]
    fig.legend(handles, names, loc="upper center", bbox_to_anchor=(0.5, 0.965), ncol=min(len(names), 7),
               fontsize=7, frameon=False)


Limits = Mapping[str, Sequence[tuple[str, float]]]
SETUP = ("move_to_start", "tare")  # before the tare the F/T sensor still carries its unloaded offset
OFF_SCALE = 2.6  # a limit beyond this many times the data's reach is named at the edge, not drawn


def _limits(ax: Any, entries: Sequence[tuple[str, float]], unit: str, signed: bool = False) -> None:
    """The limits on `ax` as dashed lines (also below zero when `signed`), those far beyond the data named
    at the top edge instead, so the data keep the scale."""
    lo, hi = ax.get_ylim()
    reach = max(abs(lo), abs(hi))
    shown, named = [], []
    for i, (name, value) in enumerate(entries):
        colour = ("tab:red", "darkred", "black")[min(i, 2)]
        if value <= OFF_SCALE * reach:
            for v in ((value, -value) if signed else (value,)):
                ax.axhline(v, color=colour, lw=0.9, ls=(0, (6, 3)))
            shown.append(value)
            ax.text(0.995, value, f"{name} {value:g} {unit}", transform=ax.get_yaxis_transform(), fontsize=7,
                    color=colour, va="bottom", ha="right")
        else:
            named.append(f"{name} {value:g} {unit}")
    if shown:
        top = max(shown) * 1.08
        ax.set_ylim(min(lo, -top) if signed else lo, max(hi, top * 1.05))
    if named:
        ax.text(0.005, 0.97, "off the scale: " + ", ".join(named), transform=ax.transAxes, fontsize=7,
                ha="left", va="top", color="darkred")


def _mark_peak(ax: Any, t: np.ndarray, values: np.ndarray, states: list[str], label: str, colour: str,
               row: int = 0) -> None:
    """Mark the largest (pressing) force after the tare, its size written beside it (`row`: one line of text
    per marked series, so two peaks close in time stay readable)."""
    ok = ~np.isin(np.asarray(states), SETUP) & np.isfinite(values)
    if not ok.any():
        return
    i = int(np.flatnonzero(ok)[np.argmax(values[ok])])
    ax.plot(t[i], values[i], "v", color=colour, ms=7, zorder=5, mec="white", mew=0.6)
    ax.annotate(f"{label} {values[i]:.1f} N at {t[i]:.2f} s", (t[i], values[i]), textcoords="offset points",
                xytext=(10, -4 - 11 * row), fontsize=7, color=colour, va="top",
                bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8})


def plot_force_run(table: pa.Table, path: Path, title: str, setpoint_col: str = "fz_setpoint",
                   force_label: str = "Fz used by the controller", limits: Limits | None = None) -> Path:
    d = table.to_pydict()
    t = np.asarray(d["t"])
    states = [str(s) for s in d["state"]]
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(10, 7), height_ratios=[2, 1])
    _shade_states(fig, [ax], t, states)
    if "sensor_fz" in d:
        ax.plot(t, d["fz"], color="tab:orange", lw=1, label=force_label)
        ax.plot(t, d["sensor_fz"], color="tab:green", lw=1, label="Fz measured (F/T sensor)")
    else:
        ax.plot(t, d["fz"], color="tab:green", lw=1, label="Fz measured (F/T sensor)")
    if setpoint_col in d:
        ax.plot(t, d[setpoint_col], "r--", lw=1.2, label="setpoint")
    measured = np.asarray(d["sensor_fz"] if "sensor_fz" in d else d["fz"], float)
    _mark_peak(ax, t, measured, states, "F/T Fz peak", "tab:green")
    if "sensor_fz" in d:
        _mark_peak(ax, t, np.asarray(d["fz"], float), states, "virtual Fz peak", "tab:orange", row=1)
    if limits and limits.get("fz"):
        _limits(ax, limits["fz"], "N")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("normal force Fz [N]")
    fig.suptitle(title)
    ax.legend(loc="lower right", fontsize=8, ncol=3)
    ax.grid(alpha=0.3)
    if "ref_x" in d:
        ax2.plot(d["ref_x"], d["ref_y"], lw=1)
        ax2.set_xlabel("TCP reference x [m]")
        ax2.set_ylabel("y [m]")
        ax2.set_title("path on the table (base frame)")
        ax2.set_aspect("equal", adjustable="datalim")
        ax2.grid(alpha=0.3)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_peg_run(table: pa.Table, path: Path, title: str, limits: Limits | None = None) -> Path:
    """The peg-in-hole run like the paper's Fig. 16: peg position and depth, Fz, and (Mx, My) over time,
    virtual (used by the controller) and measured (F/T sensor) where both were logged, states shaded, the
    limits and the peak force marked, and the contact as the task classified it."""
    d = table.to_pydict()
    t = np.asarray(d["t"])
    states = [str(s) for s in d["state"]]
    fig, axes = plt.subplots(4, 1, figsize=(10, 10), sharex=True, height_ratios=[1.2, 1, 1, 0.5])
    _shade_states(fig, list(axes[:3]), t, states)
    for ax in axes[:3]:
        ax.grid(alpha=0.3)
    ax = axes[0]
    if "depth" in d:
        ax.plot(t, np.asarray(d["depth"], float) * 1e3, color="tab:green", lw=1.2, label="depth below the mouth")
    for key, colour in (("tip_x", "tab:blue"), ("tip_y", "tab:purple")):
        if key in d:
            v = np.asarray(d[key], float)
            ax.plot(t, (v - v[0]) * 1e3, color=colour, lw=1, label=f"{key[-1]} - start")
    ax.set_ylabel("peg [mm]")
    fig.suptitle(title)
    ax.legend(loc="lower right", fontsize=7, ncol=3)
    used = "virtual" if "sensor_fz" in d else "F/T sensor"
    for ax, keys, unit in ((axes[1], ("fz",), "N"), (axes[2], ("mx", "my"), "N·m")):
        for key, colour in zip(keys, ("tab:red", "tab:orange"), strict=False):
            ax.plot(t, d[key], color=colour, lw=1, label=f"{key.capitalize()} ({used})")
            if f"sensor_{key}" in d:
                ax.plot(t, d[f"sensor_{key}"], color=colour, lw=0.8, ls="--", alpha=0.8,
                        label=f"{key.capitalize()} (F/T sensor)")
        if keys == ("fz",) and "fz_setpoint" in d:
            ax.plot(t, d["fz_setpoint"], "k:", lw=1, label="Fz setpoint")
        if keys == ("fz",):
            measured = np.asarray(d["sensor_fz"] if "sensor_fz" in d else d["fz"], float)
            _mark_peak(ax, t, measured, states, "F/T Fz peak", "tab:red")
            if "sensor_fz" in d:
                _mark_peak(ax, t, np.asarray(d["fz"], float), states, "virtual Fz peak", "darkorange", row=1)
        ax.set_ylabel(f"[{unit}]")
        ax.legend(loc="lower left", fontsize=7, ncol=3)
    if limits:
        if limits.get("fz"):
            _limits(axes[1], limits["fz"], "N")
        moments = [e for e in limits.get("mx", ()) if e in limits.get("my", ())]
        if moments:
            _limits(axes[2], moments, "N·m", signed=True)
    column = "contact_state" if "contact_state" in d else "contact"
    if column in d:
        # The contact as the task classified it (the probe's verdict carried through the states it chose).
        kinds = ["free", "stuck_outside", "stuck_inside", "aligned"]
        code = [kinds.index(c) if c in kinds else -1 for c in d[column]]
        axes[3].step(t, code, where="post", color="k", lw=1)
        axes[3].set_yticks(range(len(kinds)), kinds, fontsize=7)
        axes[3].set_ylim(-0.5, len(kinds) - 0.5)
        axes[3].set_ylabel("contact\n(classified)", fontsize=8)
        axes[3].grid(alpha=0.3)
    axes[3].set_xlabel("time [s]")
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
