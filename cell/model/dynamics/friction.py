"""Joint-loss terms beyond B_m q'' + C_m q' + f_c sign(q'): their names, and their regressor columns per joint."""

from __future__ import annotations

import numpy as np

from drivers.configio import require

# Extra loss terms a P2 may carry (each a per-joint coefficient, linear in the torque):
# * offset: a constant torque (asymmetric Coulomb friction: f_c+ != f_c- shows as f_c sign + offset);
# * viscous_asym: |q'| (viscous friction that differs between the two directions);
# * stribeck: sign(q') exp(-(q'/v_s)^2) at v_s = 0.02 and 0.1 rad/s (the friction peak at low speed);
# * load: |tau_rigid| sign(q') (gear friction that grows with the torque the gear transmits).
EXTRA_TERMS: dict[str, int] = {"offset": 1, "viscous_asym": 1, "stribeck": 2, "load": 1}
STRIBECK_SPEEDS = (0.02, 0.1)  # rad/s


def validate_terms(terms: tuple[str, ...] | list[str], where: str) -> None:
    for t in terms:
        require(t in EXTRA_TERMS, where, f"unknown loss term {t!r} (known: {', '.join(EXTRA_TERMS)})")
    require(len(set(terms)) == len(terms), where, "lists a loss term twice")


def term_names(terms: tuple[str, ...] | list[str]) -> list[str]:
    """One name per coefficient column, in `extra_columns` order."""
    names: list[str] = []
    for t in terms:
        names += [f"{t}{k}" for k in range(EXTRA_TERMS[t])] if EXTRA_TERMS[t] > 1 else [t]
    return names


def extra_columns(terms: tuple[str, ...] | list[str], dq: np.ndarray, sign: np.ndarray,
                  rigid: np.ndarray | None) -> np.ndarray:
    """(..., n, k) regressor columns of the extra terms for joint states `dq` (..., n); `sign` is the
    smoothed sign of dq the Coulomb term uses; `rigid` the rigid-body torque (needed by `load`)."""
    cols: list[np.ndarray] = []
    for t in terms:
        if t == "offset":
            cols.append(np.ones_like(dq))
        elif t == "viscous_asym":
            cols.append(np.abs(dq))
        elif t == "stribeck":
            cols += [sign * np.exp(-((dq / vs) ** 2)) for vs in STRIBECK_SPEEDS]
        elif t == "load":
            if rigid is None:
                raise ValueError("the 'load' loss term needs the rigid-body torque")
            cols.append(np.abs(rigid) * sign)
        else:
            raise ValueError(f"unknown loss term {t!r}")
    if not cols:
        return np.zeros((*dq.shape, 0))
    return np.stack(cols, axis=-1)
