"""Where the project's model files live, in a source checkout or an installed wheel."""

from __future__ import annotations

from pathlib import Path

_PACKAGE_DIR = Path(__file__).resolve().parent


def assets_dir() -> Path:
    """The ``assets/`` folder: ``beavr_sim/_assets`` in a wheel, the repository's otherwise."""
    for candidate in (_PACKAGE_DIR / "_assets", _PACKAGE_DIR.parent / "assets"):
        if (candidate / "mjcf").is_dir():
            return candidate
    raise FileNotFoundError(
        f"beavr_sim assets not found next to {_PACKAGE_DIR}; reinstall the package "
        "(pip install -e .) from a full checkout."
    )


def mjcf_path(*parts: str) -> Path:
    """Path of a file under ``assets/mjcf``, checked to exist."""
    path = assets_dir().joinpath("mjcf", *parts)
    if not path.is_file():
        raise FileNotFoundError(f"MJCF file missing: {path}")
    return path


#: Embodiments whose bundled traces live in ``assets/traces/<embodiment>/`` (the others' in
#: ``assets/traces/``, recorded on the default single-arm rig).
TRACE_FOLDERS = ("rx1",)


def bundled_trace(task: str, embodiment: str | None = None) -> Path:
    """The VR trace bundled for ``task`` (task in snake case): ``assets/traces/<task>.mcap``,
    or ``assets/traces/<embodiment>/<task>.mcap`` for an embodiment in :data:`TRACE_FOLDERS`."""
    import re

    stem = re.sub(r"(?<!^)(?=[A-Z])", "_", task).lower()
    folder = assets_dir() / "traces"
    if embodiment in TRACE_FOLDERS:
        folder = folder / embodiment
    return folder / f"{stem}.mcap"
