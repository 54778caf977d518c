"""Do the safety tests catch what they claim? ``python -m beavr_sim.bench mutations``.

Each :data:`MUTATIONS` entry names a safety rule, one realistic bug in the code that enforces it
(an exact search / replace on one source file) and the tests that claim the rule. The check
copies the repository to a temporary folder, plants the bug there, and runs those tests on the
copy (pytest in a subprocess, ``PYTHONPATH`` set to the copy): the bug is *caught* when they
fail, it *survived* when they pass. A snippet that no longer matches its file exactly once is
*stale* (the code moved on: refresh the snippet), never silently skipped; tests that fail with
no bug planted (the baseline, run once per distinct test selection) make their mutations an
*error*, as does a pytest that could not run them.

Usage::

    python -m beavr_sim.bench mutations [--only NAME[,NAME...]] [--list] [--json FILE]
        [--timeout S] [--no-baseline] [--repo DIR]

A table (rule, status, seconds) and ``caught / total`` go to stdout, one JSON document to
``--json``; the exit status is 1 unless every mutation was caught. Minutes per mutation: not part of ``make test``; the figures are in
docs/benchmarks.md. Every snippet names code of this repository; after a refactor, stale ones
are listed first in the table.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from beavr_sim.naming import UnknownNameError, check_name

#: What a mutation's run can come to.
STATUSES = ("caught", "survived", "stale", "error", "timeout")
#: Not copied: version control, environments, caches that are not numba's, outputs.
_IGNORED = (
    ".git",
    ".venv",
    ".pytest_cache",
    ".ruff_cache",
    ".hypothesis",
    "*.egg-info",
    "*.pyc",
    "out",
    "build",
    "dist",
    "test-artifacts",
    "MUJOCO_LOG.TXT",
)
REPO_ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Mutation:
    """One planted bug: ``search`` (exactly once in ``path``) becomes ``replace``; ``tests``:
    the pytest arguments (files, node ids, ``-k`` expressions) of the tests that claim
    ``rule``."""

    name: str
    rule: str
    path: str
    search: str
    replace: str
    tests: tuple[str, ...]

    def __post_init__(self) -> None:
        if not self.name or not self.name.replace("-", "").replace("_", "").isalnum():
            raise ValueError(f"mutation name must be letters, digits, '-', '_': {self.name!r}")
        if self.search == self.replace:
            raise ValueError(f"mutation {self.name}: replace equals search (plants nothing)")
        if not self.tests:
            raise ValueError(f"mutation {self.name}: no tests claim its rule")


@dataclass(frozen=True)
class MutationResult:
    name: str
    rule: str
    status: str
    seconds: float
    #: Why (stale: what did not match; caught: the first failing test; error: pytest's tail).
    detail: str = ""


_GUARD = ("tests/test_guard.py",)
_TWIN = ("tests/test_guard.py", "tests/test_twin_limits.py")
_MIRROR_HOLDS = ("tests/test_hardware_mirror.py::test_timeout_estop_and_failure_hold",)

#: The safety rules, one planted bug each.
MUTATIONS: tuple[Mutation, ...] = (
    Mutation(
        "guard-non-finite",
        "guard: a NaN target is refused (non-finite)",
        "beavr_sim/twin/kernels.py",
        "        if not math.isfinite(q):\n            code = NON_FINITE",
        "        if math.isinf(q):\n            code = NON_FINITE",
        _TWIN,
    ),
    Mutation(
        "guard-joint-limit",
        "guard: a target past a joint's upper limit is refused",
        "beavr_sim/twin/kernels.py",
        "        elif q < lower[i] or q > upper[i]:",
        "        elif q < lower[i]:",
        _TWIN,
    ),
    Mutation(
        "guard-velocity",
        "guard: no joint faster than its speed cap (a 10x looser rule)",
        "beavr_sim/twin/guard.py",
        "            fast = self.rate_limit.exceeds(action - previous, self.dt)",
        "            fast = self.rate_limit.exceeds(action - previous, 10 * self.dt)",
        _GUARD,
    ),
    Mutation(
        "guard-velocity-stream",
        "guard: the same 10x looser speed rule, against the generated command streams alone",
        "beavr_sim/twin/guard.py",
        "            fast = self.rate_limit.exceeds(action - previous, self.dt)",
        "            fast = self.rate_limit.exceeds(action - previous, 10 * self.dt)",
        ("tests/test_guard.py::test_every_accepted_command_keeps_every_rule",),
    ),
    Mutation(
        "guard-speed-cap",
        "guard and twin step limit: the xArm's cap is pi rad/s (a 10x looser default)",
        "beavr_sim/twin/guard.py",
        "    arm_max_velocity: float = math.pi\n",
        "    arm_max_velocity: float = 10 * math.pi\n",
        _TWIN,
    ),
    Mutation(
        "guard-acceleration",
        "guard: no reversal at full speed within a tick (acceleration of the signed velocity)",
        "beavr_sim/twin/kernels.py",
        "            elif abs(v - velocity[i]) > amax[i] * dt * tol:",
        "            elif abs(v) - abs(velocity[i]) > amax[i] * dt * tol:",
        _GUARD,
    ),
    Mutation(
        "guard-workspace-extent",
        "guard: the workspace floor holds for each geom's whole box, not its centre",
        "beavr_sim/twin/kernels.py",
        "            if centre[k, i] - half[k, i] < lower[k, i] or "
        "centre[k, i] + half[k, i] > upper[k, i]:",
        "            if centre[k, i] < lower[k, i] or centre[k, i] > upper[k, i]:",
        ("tests/test_guard.py", "tests/test_extents.py"),
    ),
    Mutation(
        "guard-finger-tolerance",
        "guard: fingers at most 12 mm into the table (a looser tolerance)",
        "beavr_sim/twin/guard.py",
        "    finger_workspace_tolerance: float = 0.012\n",
        "    finger_workspace_tolerance: float = 0.03\n",
        _GUARD,
    ),
    Mutation(
        "guard-contact-tolerance",
        "guard: a contact is as deep as the stricter geom's tolerance allows",
        "beavr_sim/twin/guard.py",
        "        deep = dist < -np.minimum(self._tolerance[g1], self._tolerance[g2])",
        "        deep = dist < -np.maximum(self._tolerance[g1], self._tolerance[g2])",
        _GUARD,
    ),
    Mutation(
        "guard-path",
        "guard: workspace and contacts hold along the path, not only at its end",
        "beavr_sim/twin/guard.py",
        "            n = min(self.config.max_path_samples, "
        "math.ceil(step / self.config.path_resolution))",
        "            n = 1",
        _GUARD,
    ),
    Mutation(
        "guard-fixtures-static",
        "guard: the task's fixtures (mocap bodies) are static obstacles, not free objects",
        "beavr_sim/twin/guard.py",
        "                weld == 0 or model.body_mocapid[weld] >= 0 or "
        "body_name.startswith(BODY_PREFIX)",
        "                weld == 0 or body_name.startswith(BODY_PREFIX)",
        _GUARD,
    ),
    Mutation(
        "guard-fixtures-follow-resets",
        "guard: the fixtures' poses as each reset placed them (learned once only)",
        "beavr_sim/twin/twin.py",
        "            data = self.env.data\n"
        "            self.guard.set_fixtures(data.mocap_pos, data.mocap_quat)\n",
        "            data = self.env.data\n"
        "            if not self.guard.checks:\n"
        "                self.guard.set_fixtures(data.mocap_pos, data.mocap_quat)\n",
        _GUARD,
    ),
    Mutation(
        "guard-refused-holds",
        "guard: a refused effector holds its last accepted target",
        "beavr_sim/twin/guard.py",
        "        for name in verdict.blocked:\n"
        "            safe[slices[name]] = previous[slices[name]]\n",
        "        for name in verdict.blocked:\n            pass\n",
        (
            "tests/test_guard.py",
            "tests/test_hardware_mirror.py::test_adversarial_commands_never_reach_a_motor",
        ),
    ),
    Mutation(
        "twin-step-limit",
        "twin: no joint target further than its speed cap allows in one period",
        "beavr_sim/twin/twin.py",
        "        limited = self.rate_limit.clamp(previous, action, self.dt)",
        "        limited = self.rate_limit.clamp(previous, action, 10 * self.dt)",
        ("tests/test_twin_limits.py",),
    ),
    Mutation(
        "rate-limit-clamp",
        "rate limit: a joint beyond reach stops at its reach (the twin's step limit)",
        "beavr_sim/twin/rate_limit.py",
        "            out[i] = min(max(q, p - r), p + r)",
        "            out[i] = min(max(q, p - 10 * r), p + 10 * r)",
        ("tests/test_rate_limit.py", "tests/test_twin_limits.py"),
    ),
    Mutation(
        "rate-limit-non-finite",
        "rate limit: a NaN or inf target holds its joint",
        "beavr_sim/twin/rate_limit.py",
        "        if bad:\n            out[i] = p\n",
        "        if bad:\n            out[i] = q\n",
        ("tests/test_rate_limit.py",),
    ),
    Mutation(
        "mirror-catch-up-refusal",
        "mirror: a catch-up target its guard refuses is not sent",
        "beavr_sim/hardware/mirror/hardware_mirror.py",
        "            if not verdict.ok:\n"
        "                for name in verdict.blocked:\n"
        "                    sl = self.joints.slices[name]\n"
        "                    target[sl] = previous[sl]\n",
        "            if not verdict.ok:\n",
        (
            "tests/test_safety_mutations_mirror.py",
            "tests/test_hardware_mirror.py::test_catch_up_speed_is_the_same_at_any_submit_rate",
        ),
    ),
    Mutation(
        "mirror-rate-limit",
        "mirror: bunched submits are slowed to the speed cap over their spacing",
        "beavr_sim/hardware/mirror/hardware_mirror.py",
        "            limited = self.speeds.rate.clamp(previous, action, interval)",
        "            limited = self.speeds.rate.clamp(previous, action, 10 * interval)",
        ("tests/test_hardware_mirror.py::test_bunched_submits_are_slowed_to_the_speed_cap",),
    ),
    Mutation(
        "mirror-catch-up-speed",
        "mirror: a catch-up moves at the catch-up speed, whatever the submit rate",
        "beavr_sim/hardware/mirror/catch_up.py",
        "        target = self.limit.clamp(previous, action, interval).target",
        "        target = self.limit.clamp(previous, action, 10 * interval).target",
        ("tests/test_hardware_mirror.py::test_catch_up_speed_is_the_same_at_any_submit_rate",),
    ),
    Mutation(
        "mirror-timeout-hold",
        "mirror: every device holds when no fresh command came within the timeout",
        "beavr_sim/hardware/mirror/link.py",
        "                if time.monotonic() - d.t_submit > timeout:",
        "                if time.monotonic() - d.t_submit > 100 * timeout:",
        _MIRROR_HOLDS,
    ),
    Mutation(
        "mirror-estop-latch",
        "mirror: an e-stop holds every device until released",
        "beavr_sim/hardware/mirror/board.py",
        "        if self.estop:\n            return HoldReason.ESTOP,",
        "        if False:\n            return HoldReason.ESTOP,",
        _MIRROR_HOLDS,
    ),
    Mutation(
        "mirror-failure-holds-others",
        "mirror: one device failing holds every other",
        "beavr_sim/hardware/mirror/board.py",
        "            if j != k and other.state in OUT:",
        "            if False:",
        _MIRROR_HOLDS,
    ),
    Mutation(
        "mirror-divergence-hold",
        "mirror: a device whose measured joints stay far from the twin's holds",
        "beavr_sim/hardware/mirror/divergence.py",
        "        if divergence <= self.limit:",
        "        if divergence <= 10 * self.limit:",
        ("tests/test_hardware_mirror.py::test_divergence_holds_the_device",),
    ),
    Mutation(
        "mirror-episode-fixtures",
        "mirror: its guard checks catch-ups against this episode's fixtures (begin_episode)",
        "beavr_sim/hardware/mirror/hardware_mirror.py",
        "            self.guard.set_fixtures(fixtures.mocap_pos, fixtures.mocap_quat)",
        "            pass",
        ("tests/test_safety_mutations_mirror.py", "tests/test_mirror_sessions.py"),
    ),
    Mutation(
        "dataset-discard",
        "datasets: a discarded episode's frames are in no saved episode",
        "beavr_sim/datasets/writer.py",
        "            self._dataset.clear_episode_buffer()",
        "            pass",
        ("tests/test_datasets.py::test_episodes_start_stop_and_discard_on_request",),
    ),
    Mutation(
        "operator-tracking-flags",
        "operator: a joint flagged untracked is not used, whatever its coordinates",
        "beavr_sim/operator/kernels.py",
        "        ok = tracked[i]\n",
        "        ok = True\n",
        ("tests/test_operator_robustness.py",),
    ),
    Mutation(
        "operator-non-finite-joints",
        "operator: a joint flagged tracked but NaN/inf is used as untracked",
        "beavr_sim/operator/kernels.py",
        "                if not np.isfinite(joints[i, a]):\n                    ok = False\n",
        "                if not np.isfinite(joints[i, a]):\n                    pass\n",
        ("tests/test_operator_robustness.py",),
    ),
    Mutation(
        "quest-untracked-zeros",
        "Quest parser: joints sent as 0,0,0 are untracked",
        "beavr_sim/headset/quest_protocol.py",
        "    untracked = ~points.any(axis=1)\n",
        "    untracked = np.zeros(N_JOINTS, dtype=bool)\n",
        ("tests/test_quest_protocol.py",),
    ),
    Mutation(
        "quest-too-far",
        "Quest parser: coordinates beyond 10 m are refused (too_far)",
        "beavr_sim/headset/quest_protocol.py",
        "    far = np.abs(points).max(axis=1) > MAX_ABS_COORD_M\n",
        "    far = np.abs(points).max(axis=1) > 100 * MAX_ABS_COORD_M\n",
        ("tests/test_quest_protocol.py",),
    ),
)


def find(names: Iterable[str], mutations: Sequence[Mutation] = MUTATIONS) -> list[Mutation]:
    """The mutations named (in the order given); an unknown name lists the valid ones."""
    by_name = {m.name: m for m in mutations}
    return [by_name[check_name("mutation", n, list(by_name))] for n in names]


def copy_repository(repo: Path, dest: Path) -> Path:
    """A copy of ``repo`` at ``dest`` for planting bugs in: sources, tests, assets and numba's
    on-disk caches (modification times kept, so unchanged kernels are not compiled again)."""
    shutil.copytree(repo, dest, ignore=shutil.ignore_patterns(*_IGNORED), symlinks=True)
    return dest


def stale(mutation: Mutation, root: Path) -> str:
    """Why ``mutation`` cannot be planted under ``root`` (its snippet is not in its file
    exactly once), or "" when it can."""
    path = root / mutation.path
    if not path.is_file():
        return f"{mutation.path} does not exist"
    count = path.read_text().count(mutation.search)
    if count == 1:
        return ""
    first = mutation.search.strip().splitlines()[0][:60]
    where = "not found" if count == 0 else f"found {count} times"
    return f"snippet {first!r}... {where} in {mutation.path}"


def plant(mutation: Mutation, root: Path) -> str:
    """Apply ``mutation`` under ``root``; "" when planted, else why it is stale."""
    why = stale(mutation, root)
    if not why:
        path = root / mutation.path
        path.write_text(path.read_text().replace(mutation.search, mutation.replace))
    return why


def _pytest(
    root: Path,
    tests: Sequence[str],
    python: str,
    timeout_s: float,
    extra_env: Mapping[str, str] | None = None,
):
    """Run ``tests`` on the copy at ``root``: (return code or None on timeout, output)."""
    env = {**os.environ, **(extra_env or {}), "PYTHONPATH": str(root)}
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    env.setdefault("MUJOCO_GL", "egl")
    cmd = [python, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests]
    try:
        done = subprocess.run(
            cmd, cwd=root, env=env, capture_output=True, text=True, timeout=timeout_s
        )
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode(errors="replace") if isinstance(exc.stdout, bytes) else ""
        return None, out or ""
    return done.returncode, done.stdout + done.stderr


def _first_failure(output: str) -> str:
    for line in output.splitlines():  # pytest's summary lines, not captured log records
        if line.startswith(("FAILED ", "ERROR ")) and "::" in line.split(" ", 2)[1]:
            return line[:200]
    lines = [line for line in output.splitlines() if line.strip()]
    return lines[-1][:200] if lines else ""


def run_one(
    mutation: Mutation,
    repo: Path,
    python: str = sys.executable,
    timeout_s: float = 900.0,
    extra_env: Mapping[str, str] | None = None,
) -> MutationResult:
    """Plant ``mutation`` in a fresh copy of ``repo`` and run its tests there (``extra_env``:
    more environment variables for pytest)."""
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix=f"mutant-{mutation.name}-") as tmp:
        root = copy_repository(repo, Path(tmp) / "repo")
        why = plant(mutation, root)
        if why:
            return MutationResult(mutation.name, mutation.rule, "stale", 0.0, why)
        code, output = _pytest(root, mutation.tests, python, timeout_s, extra_env)
    seconds = round(time.perf_counter() - t0, 1)
    if code is None:
        status, detail = "timeout", f"tests ran past {timeout_s:g} s"
    elif code == 0:
        status, detail = "survived", "every test passed with the bug planted"
    elif code == 1:
        status, detail = "caught", _first_failure(output)
    else:  # 2 interrupted / collection error, 3 internal, 4 usage, 5 no tests collected
        status, detail = "error", f"pytest exit {code}: {_first_failure(output)}"
    return MutationResult(mutation.name, mutation.rule, status, seconds, detail)


def baseline(
    tests: Sequence[str],
    repo: Path,
    python: str = sys.executable,
    timeout_s: float = 900.0,
    extra_env: Mapping[str, str] | None = None,
) -> str:
    """ "" when ``tests`` pass on an unmutated copy of ``repo``, else what went wrong."""
    with tempfile.TemporaryDirectory(prefix="mutant-baseline-") as tmp:
        root = copy_repository(repo, Path(tmp) / "repo")
        code, output = _pytest(root, tests, python, timeout_s, extra_env)
    if code == 0:
        return ""
    why = "timed out" if code is None else f"exit {code}: {_first_failure(output)}"
    return f"the tests fail with no bug planted ({why})"


def run(
    mutations: Sequence[Mutation],
    repo: Path = REPO_ROOT,
    python: str = sys.executable,
    timeout_s: float = 900.0,
    check_baseline: bool = True,
    progress: Callable[[MutationResult], None] | None = None,
    extra_env: Mapping[str, str] | None = None,
) -> list[MutationResult]:
    """Every mutation, one at a time (stale ones first, they cost nothing)."""
    results: list[MutationResult] = []
    why = {m.name: stale(m, repo) for m in mutations}
    baselines: dict[tuple[str, ...], str] = {}
    ordered = [m for m in mutations if why[m.name]] + [m for m in mutations if not why[m.name]]
    for m in ordered:
        if why[m.name]:
            result = MutationResult(m.name, m.rule, "stale", 0.0, why[m.name])
        else:
            if check_baseline and m.tests not in baselines:
                baselines[m.tests] = baseline(m.tests, repo, python, timeout_s, extra_env)
            problem = baselines.get(m.tests, "")
            if problem:
                result = MutationResult(m.name, m.rule, "error", 0.0, problem)
            else:
                result = run_one(m, repo, python, timeout_s, extra_env)
        results.append(result)
        if progress is not None:
            progress(result)
    return results


def score(results: Sequence[MutationResult]) -> dict:
    """``caught`` of ``total`` (every mutation listed: stale, errors and timeouts count against
    it), and the count per status."""
    counts = {s: sum(r.status == s for r in results) for s in STATUSES}
    return {"caught": counts["caught"], "total": len(results), "by_status": counts}


def table(results: Sequence[MutationResult]) -> str:
    """A Markdown table of ``results`` and the caught / total line."""
    lines = ["| mutation | rule | result | s |", "|---|---|---|---|"]
    for r in results:
        lines.append(f"| `{r.name}` | {r.rule} | {r.status} | {r.seconds:g} |")
    s = score(results)
    others = ", ".join(f"{n} {k}" for k, n in s["by_status"].items() if n and k != "caught")
    lines.append("")
    lines.append(f"caught {s['caught']} / {s['total']}" + (f" ({others})" if others else ""))
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m beavr_sim.bench mutations",
        description=__doc__.split("\n\n")[1],
    )
    parser.add_argument("--only", default=None, help="comma-separated mutation names")
    parser.add_argument("--list", action="store_true", help="list the mutations and exit")
    parser.add_argument("--json", type=Path, default=None, metavar="FILE", help="write results")
    parser.add_argument(
        "--timeout", type=float, default=900.0, help="seconds per test run (default 900)"
    )
    parser.add_argument(
        "--no-baseline",
        action="store_true",
        help="do not first run each test selection with no bug planted",
    )
    parser.add_argument(
        "--repo", type=Path, default=REPO_ROOT, help="the repository to copy (default this one)"
    )
    args = parser.parse_args(argv)
    mutations = list(MUTATIONS)
    if args.only:
        try:
            mutations = find([n.strip() for n in args.only.split(",") if n.strip()])
        except UnknownNameError as exc:
            parser.error(str(exc))
    if args.list:
        for m in mutations:
            print(f"{m.name:32} {m.path:40} {m.rule}")
        return 0

    def progress(r: MutationResult) -> None:
        print(f"{r.name}: {r.status} ({r.seconds:g} s) {r.detail}", file=sys.stderr, flush=True)

    results = run(
        mutations,
        args.repo.resolve(),
        timeout_s=args.timeout,
        check_baseline=not args.no_baseline,
        progress=progress,
    )
    print(table(results))
    if args.json is not None:
        document = {
            "command": "python -m beavr_sim.bench mutations"
            + (f" --only {args.only}" if args.only else ""),
            **score(results),
            "results": [asdict(r) for r in results],
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(document, indent=2) + "\n")
    return 0 if score(results)["caught"] == len(results) else 1
