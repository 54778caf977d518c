"""Joint-name dictionaries (LeRobot's robot actions and observations) <-> action vectors.

LeRobot robots and teleoperators exchange flat ``{name: float}`` dicts; beavr_sim's env, twin
and datasets use one vector in the embodiment's action order. The names are the embodiment's
joint names (``right/joint1``, ..., ``right/leap_15``), the same as the ``names`` of
``observation.state`` and ``action`` in a ``beavr_sim.datasets`` recording, so a dataset recorded
either way has the same features.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np


def joint_features(names: Sequence[str]) -> dict[str, type]:
    """LeRobot feature dict of scalar joint values (``{name: float}``)."""
    return dict.fromkeys(names, float)


def _listing(names: Sequence[str], limit: int = 8) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f", ... ({len(names)} in all)" if len(names) > limit else "")


def action_vector(action: Mapping[str, Any], names: Sequence[str]) -> np.ndarray:
    """The values of ``action`` in the order of ``names``; raises ValueError naming missing,
    unknown and non-numeric or non-finite joints, and listing the expected names."""
    if not isinstance(action, Mapping):
        raise TypeError(
            f"an action is a dict of joint name -> target (rad), got {type(action).__name__}; "
            f"expected keys: {_listing(list(names))}"
        )
    missing = [n for n in names if n not in action]
    unknown = sorted(str(k) for k in action if k not in set(names))
    if missing or unknown:
        parts = []
        if missing:
            parts.append(f"missing joints {_listing(missing)}")
        if unknown:
            parts.append(f"unknown keys {_listing(unknown)}")
        raise ValueError(
            f"action: {'; '.join(parts)}. Expected exactly these {len(names)} joints: "
            f"{_listing(list(names))}"
        )
    out = np.empty(len(names), dtype=np.float64)
    bad = []
    for i, name in enumerate(names):
        try:
            out[i] = float(action[name])
        except (TypeError, ValueError):
            bad.append(name)
            continue
        if not math.isfinite(out[i]):
            bad.append(name)
    if bad:
        raise ValueError(f"action: non-numeric or non-finite targets for joints {_listing(bad)}")
    return out


def action_dict(values: np.ndarray, names: Sequence[str]) -> dict[str, float]:
    """``{name: value}`` in the order of ``names``."""
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (len(names),):
        raise ValueError(f"expected {len(names)} joint values, got shape {values.shape}")
    return {name: float(v) for name, v in zip(names, values, strict=True)}
