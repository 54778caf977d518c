from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")

from beavr_sim.reference import find_reference_dir


@pytest.fixture(scope="session")
def reference_dir() -> Path:
    found = find_reference_dir()
    if found is None:
        pytest.skip(
            "reference models not found: ../shared/reference beside the checkout "
            "(or $BEAVR_REFERENCE_DIR) is absent"
        )
    return found
