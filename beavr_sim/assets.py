"""Where the project's model files live, in a source checkout or an installed wheel."""

from __future__ import annotations

import re
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


#: The embodiment of the traces in ``assets/traces/`` itself (a one-armed rig's recordings).
DEFAULT_TRACE_EMBODIMENT = "xarm7_leap_right"
#: Embodiments whose bundled traces live in ``assets/traces/<embodiment>/``.
TRACE_FOLDERS = ("rx1", "xarm7_leap_bimanual")


def task_stem(task: str) -> str:
    """A task's file stem: ``PickPlace`` -> ``pick_place`` (``pick_place`` stays)."""
    return re.sub(r"(?<!^)(?<!_)(?=[A-Z])", "_", task).lower()


def bundled_traces() -> dict[str, tuple[str, ...]]:
    """The bundled traces: embodiment -> the task stems it has a trace for."""
    folder = assets_dir() / "traces"
    found = {DEFAULT_TRACE_EMBODIMENT: tuple(sorted(p.stem for p in folder.glob("*.mcap")))}
    for embodiment in TRACE_FOLDERS:
        found[embodiment] = tuple(sorted(p.stem for p in (folder / embodiment).glob("*.mcap")))
    return found


def synth_command(task: str, embodiment: str | None = None) -> str:
    """The command that synthesizes a trace of ``task`` on ``embodiment`` from its expert."""
    stem = task_stem(task)
    embodiment = embodiment or DEFAULT_TRACE_EMBODIMENT
    out = stem if embodiment == DEFAULT_TRACE_EMBODIMENT else f"{stem}_{embodiment}"
    return (
        f"python -m beavr_sim.traces synth --task {stem} --embodiment {embodiment} "
        f"--seed 0 --tries 10 --out {out}.mcap"
    )


def bundled_trace(task: str, embodiment: str | None = None) -> Path:
    """The VR trace bundled for ``task`` on ``embodiment`` (default
    :data:`DEFAULT_TRACE_EMBODIMENT`): ``assets/traces/<task>.mcap``, or
    ``assets/traces/<embodiment>/<task>.mcap`` for an embodiment in :data:`TRACE_FOLDERS`.

    Raises ``FileNotFoundError`` naming the bundled traces and the ``traces synth`` command
    that makes the missing one. The names are not checked here (this module sits below tasks
    and embodiments): :func:`beavr_sim.traces.bundled.find_bundled_trace` checks them first.
    """
    stem = task_stem(task)
    embodiment = embodiment or DEFAULT_TRACE_EMBODIMENT
    folder = assets_dir() / "traces"
    if embodiment != DEFAULT_TRACE_EMBODIMENT:
        folder = folder / embodiment
    path = folder / f"{stem}.mcap"
    if not path.is_file():
        listing = "; ".join(
            f"{name}: {', '.join(stems) or 'none'}" for name, stems in bundled_traces().items()
        )
        command = synth_command(task, embodiment)
        out = command.rpartition(" ")[2]
        raise FileNotFoundError(
            f"no bundled trace of {stem} on {embodiment} ({path} does not exist). Bundled "
            f"traces: {listing}. Make one from the task's expert with `{command}` and pass "
            f"--trace {out}"
        )
    return path
