"""``python -m beavr_sim.hardware.guard --embodiment E --qpos-file F.npy [--stream --hz 30]``.

Checks joint targets with the guard that stands before every hardware write
(:class:`beavr_sim.twin.guard.CollisionGuard`) on the embodiment's scene without task objects.
``F.npy`` holds an (N, n) array of targets in ``agent_pos`` order (n = the embodiment's joints).

- Without ``--stream`` each row is checked alone, as a commanded configuration (non-finite,
  joint limits, workspace, contacts).
- With ``--stream`` the rows are successive commands at ``--hz`` starting from home: each is
  also checked against the speed and acceleration caps and along the path from the last
  accepted row; a refused row is not accepted (the robot would hold there).

Prints one JSON line per row, ``{"row": i, "ok": bool, "reason": str}``, the reason naming
the rule and the joints or geoms. Exit status: 0 all rows accepted, 1 some refused, 2 bad
input.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import mujoco
import numpy as np

from beavr_sim.envs.scene import build_scene_spec
from beavr_sim.naming import UnknownNameError
from beavr_sim.robots import make_embodiment
from beavr_sim.robots.embodiment import DEFAULT_EMBODIMENT
from beavr_sim.twin.guard import CollisionGuard, GuardConfig, GuardVerdict


def scene_guard(
    embodiment_name: str, config: GuardConfig | None = None, hz: float | None = None
) -> tuple[CollisionGuard, np.ndarray, np.ndarray]:
    """A guard on the embodiment's scene (no task objects), its qpos at home, and home."""
    embodiment = make_embodiment(embodiment_name)
    model = build_scene_spec(embodiment, 64, 64).compile()
    joints = embodiment.bind(model)
    data = mujoco.MjData(model)
    data.qpos[joints.qpos_adr] = joints.home
    guard = CollisionGuard(model, embodiment, joints, config, dt=None if hz is None else 1.0 / hz)
    return guard, data.qpos.copy(), joints.home.astype(np.float64)


def check_rows(
    guard: CollisionGuard, qpos: np.ndarray, home: np.ndarray, rows: np.ndarray, stream: bool
) -> list[GuardVerdict]:
    """A verdict per row (see the module docstring)."""
    verdicts = []
    previous = home.copy()
    guard.reset()
    for row in rows:
        if stream:
            previous, verdict = guard.filter(row, previous, qpos)
        else:
            verdict = guard.check(row, qpos)
        verdicts.append(verdict)
    return verdicts


#: The first bytes of a ``.npy`` file (``numpy.save``).
NPY_MAGIC = b"\x93NUMPY"


def load_rows(path: Path, n_joints: int) -> np.ndarray:
    """The (N, n_joints) float array in the ``.npy`` file ``path``; ValueError naming what is
    wrong (not a .npy file, object data, a wrong shape)."""
    with open(path, "rb") as f:
        head = f.read(len(NPY_MAGIC))
    if head != NPY_MAGIC:
        kind = "a .npz archive" if head.startswith(b"PK") else f"starts with {head!r}"
        raise ValueError(
            f"{path} is not a .npy file ({kind}); --qpos-file takes numpy.save output, e.g. "
            f"python -c \"import numpy; numpy.save('q.npy', numpy.loadtxt('q.txt'))\" for a "
            "text file of one row of joint targets per line"
        )
    try:
        rows = np.load(path, allow_pickle=False)
    except ValueError as exc:  # object arrays need pickle, which a target file never does
        raise ValueError(f"{path} holds object data, not joint targets: {exc}") from None
    rows = np.asarray(rows, dtype=np.float64)
    if rows.ndim == 1:
        rows = rows[None]
    if rows.ndim != 2 or rows.shape[1] != n_joints:
        raise ValueError(
            f"{path}: expected an (N, {n_joints}) array of joint targets in agent_pos order, "
            f"got shape {rows.shape}"
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m beavr_sim.hardware.guard",
        description=__doc__.split("\n\n")[1] if __doc__ else None,
    )
    parser.add_argument("--embodiment", default=DEFAULT_EMBODIMENT)
    parser.add_argument("--qpos-file", type=Path, required=True, help="(N, n) .npy array")
    parser.add_argument("--stream", action="store_true", help="rows are successive commands")
    parser.add_argument("--hz", type=float, default=30.0, help="command rate with --stream")
    args = parser.parse_args(argv)
    try:
        if not args.hz > 0:
            raise ValueError(f"--hz must be positive, got {args.hz}")
        guard, qpos, home = scene_guard(args.embodiment, hz=args.hz if args.stream else None)
        rows = load_rows(args.qpos_file, len(home))
    except (UnknownNameError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    refused = 0
    for i, verdict in enumerate(check_rows(guard, qpos, home, rows, args.stream)):
        refused += not verdict.ok
        print(json.dumps({"row": i, "ok": verdict.ok, "reason": verdict.reason()}))
    return 1 if refused else 0


if __name__ == "__main__":
    sys.exit(main())
