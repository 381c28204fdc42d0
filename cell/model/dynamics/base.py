"""The one interface every joint-torque model implements, and the metadata its saved artefact carries."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np


@dataclass
class ModelMeta:
    """What a saved model was made from; loading refuses an artefact whose robot does not match."""

    kind: str  # "P1", "P2", "D", "H1", "H2", "H3"
    robot: str  # robot name from the URDF, e.g. "tm5-700"
    urdf_sha256: str
    joints: int
    features: dict[str, Any] = field(default_factory=dict)  # window length, grouping, ...
    training_data_sha256: str = ""
    training_samples: int = 0
    version: int = 1
    extra: dict[str, Any] = field(default_factory=dict)


@runtime_checkable
class TorqueModel(Protocol):
    """Predicts the joint torque the arm needs for a motion (inverse dynamics incl. losses).

    Arrays are (N, n_joints) in SI units.  A model that uses a time window reads the N rows as
    consecutive samples `dt` apart and predicts for each row from that row and the ones before it
    (the first rows of a batch reuse the first sample as history).
    """

    meta: ModelMeta

    def predict(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray: ...
