"""``lerobot-train`` as a subprocess: the command of a :class:`TrainConfig`, resuming an
unfinished run from its last checkpoint (LeRobot's own ``--resume=true``), and one clear line
when it fails (with its log's path).

A run lives in ``<stage dir>/run`` (LeRobot's ``output_dir``), its output in
``<stage dir>/train.log`` (appended by a resumed run). Checkpoints are LeRobot's:
``run/checkpoints/<step:06d>/pretrained_model``.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

from beavr_sim.bench.policies.config import TrainConfig
from beavr_sim.bench.policies.train_progress import TrainProgress, follow

#: In order: our ``$ lerobot-train ...`` line before each (re)start, the progress bar's count
#: (``| 1600/6000 [``: the step, counted from the run's start or its checkpoint), and
#: LeRobot's log lines (``step:2K smpl:51K ... loss:0.227 ...``: the step rounded, 1K, 2M).
#: A command line (at a line's start, or right after the progress bar of a run killed mid-line,
#: in logs written before each command started a line), a progress bar's count, a loss line.
_LOG_EVENT = re.compile(
    r"(?m)(?:^|(?<=\]))\$ (?P<command>.*)$|\| *(?P<count>\d+)/\d+ \["
    r"|\bstep:\S+ .*?\bloss:(?P<loss>[-+0-9.eE]+)"
)
_CHECKPOINT = re.compile(r"checkpoints/(\d+)/")


class TrainFailed(RuntimeError):
    """``lerobot-train`` exited with an error; the message names its log."""


class TrainUnfinished(RuntimeError):
    """A run stopped half-way, found without ``--resume``."""


def executable() -> str:
    """``lerobot-train`` beside this Python (its venv), else on ``PATH``."""
    beside = Path(sys.executable).with_name("lerobot-train")
    if beside.exists():
        return str(beside)
    found = shutil.which("lerobot-train")
    if found is None:
        raise FileNotFoundError(
            "lerobot-train is not installed (it comes with lerobot[training]: pip install -e .)"
        )
    return found


def saved_steps(run: Path) -> list[int]:
    """The steps of the run's checkpoints, in order ([] when none was saved)."""
    folder = run / "checkpoints"
    if not folder.is_dir():
        return []
    return sorted(
        int(p.name)
        for p in folder.iterdir()
        if p.name.isdigit() and (p / "pretrained_model" / "config.json").is_file()
    )


def checkpoint(run: Path, step: int) -> Path:
    """The pretrained_model folder of the checkpoint at ``step``."""
    return run / "checkpoints" / f"{step:06d}" / "pretrained_model"


def train_command(
    config: TrainConfig,
    dataset: Path,
    repo_id: str,
    run: Path,
    device: str,
    loader_workers: int = 0,
) -> list[str]:
    """A fresh run of ``config`` on the dataset at ``dataset`` (``loader_workers``: LeRobot's
    data-loading processes; 0 loads in the training process, which is what bounds the step
    rate on a GPU)."""
    return [
        executable(),
        f"--policy.type={config.policy}",
        f"--dataset.repo_id={repo_id}",
        f"--dataset.root={dataset}",
        "--dataset.video_backend=pyav",
        f"--policy.device={device}",
        "--policy.push_to_hub=false",
        *(f"--policy.{flag}" for flag in config.policy_flags),
        f"--batch_size={config.batch_size}",
        f"--steps={config.steps}",
        f"--save_freq={config.save_freq}",
        f"--log_freq={log_freq(config)}",
        f"--num_workers={loader_workers}",
        f"--seed={config.seed}",
        "--wandb.enable=false",
        f"--output_dir={run}",
    ]


def resume_command(
    config: TrainConfig, run: Path, device: str, loader_workers: int = 0
) -> list[str]:
    """Continue the run at ``run`` from its last checkpoint up to ``config.steps``."""
    last = checkpoint(run, saved_steps(run)[-1])
    return [
        executable(),
        f"--config_path={last / 'train_config.json'}",
        "--resume=true",
        f"--steps={config.steps}",
        f"--policy.device={device}",
        f"--num_workers={loader_workers}",
        f"--output_dir={run}",
    ]


def train(
    config: TrainConfig,
    dataset: Path,
    repo_id: str,
    stage: Path,
    device: str = "cpu",
    resume: bool = False,
    loader_workers: int = 0,
) -> Path:
    """Train into ``stage/run`` (see the module docstring); returns the run folder.

    A run already there that reached ``config.steps`` is kept as it is; one with checkpoints
    short of it continues with ``resume`` and raises :class:`TrainUnfinished` without; one
    without any checkpoint starts again."""
    run = stage / "run"
    log = stage / "train.log"
    steps = saved_steps(run)
    if steps and steps[-1] >= config.steps:
        return run
    if steps and not resume:
        raise TrainUnfinished(
            f"{config.policy} on {config.demos.task}: an unfinished training run at step "
            f"{steps[-1]} of {config.steps} in {run}; pass --resume to continue it"
        )
    if steps:
        command = resume_command(config, run, device, loader_workers)
    else:
        if run.exists():
            shutil.rmtree(run)
        command = train_command(config, dataset, repo_id, run, device, loader_workers)
    stage.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled"}
    progress = TrainProgress(config.steps, first_step=steps[-1] if steps else 0)
    label = f"train {config.policy} on {config.demos.task}"
    cut_mid_line = log.is_file() and log.stat().st_size > 0 and not _ends_a_line(log)
    with log.open("a") as out:
        # A killed run's progress bar ends without a newline: the command starts its own line.
        out.write(("\n" if cut_mid_line else "") + "$ " + " ".join(command) + "\n")
        out.flush()
        process = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, env=env)
        try:
            code = follow(process, log, progress, label)
        finally:
            if process.poll() is None:  # interrupted here: the run stops with us
                process.terminate()
                try:
                    process.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
    if code != 0:
        raise TrainFailed(
            f"lerobot-train failed (exit {code}) training {config.policy} on "
            f"{config.demos.task}; its log: {log}"
        )
    done = saved_steps(run)
    if not done or done[-1] < config.steps:
        raise TrainFailed(
            f"lerobot-train ended without a checkpoint at step {config.steps} "
            f"({config.policy} on {config.demos.task}); its log: {log}"
        )
    return run


def shorter_run(train_root: Path, config: TrainConfig) -> tuple[Path, int] | None:
    """The finished training stage under ``train_root`` whose configuration is ``config``'s
    but for fewer steps (the most of them, if several), and its steps; None if there is none."""
    want = json.loads(json.dumps(asdict(config)))
    best: tuple[Path, int] | None = None
    for marker in train_root.glob(f"{config.policy}-{config.demos.task}-*/stage.json"):
        try:
            other = json.loads(marker.read_text()).get("config", {})
        except (OSError, ValueError):
            continue
        steps = other.get("steps")
        if not isinstance(steps, int) or steps >= config.steps:
            continue
        if {**other, "steps": config.steps} == want and (best is None or steps > best[1]):
            best = (marker.parent, steps)
    return best


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)  # LeRobot never rewrites a checkpoint's files: share them
    except OSError:
        shutil.copy2(src, dst)


def extend_from(source: Path, stage: Path) -> None:
    """Start ``stage``'s run as the finished run of the training stage ``source`` (its
    checkpoints and log): :func:`train` with ``resume`` then continues it from its last
    checkpoint to ``stage``'s steps."""
    stage.mkdir(parents=True, exist_ok=True)
    shutil.copytree(source / "run", stage / "run", symlinks=True, copy_function=_link_or_copy)
    if (source / "train.log").is_file():
        shutil.copy2(source / "train.log", stage / "train.log")


def _ends_a_line(log: Path) -> bool:
    with log.open("rb") as f:
        f.seek(-1, os.SEEK_END)
        return f.read(1) == b"\n"


def log_freq(config: TrainConfig) -> int:
    """Steps between LeRobot's log lines (each with the loss): 200, or every checkpoint's."""
    return max(1, min(200, config.save_freq))


def loss_curve(log: Path, every: int) -> list[tuple[int, float]]:
    """``(step, loss)`` of every logged training step in ``log``, the step exact: LeRobot
    logs every ``every`` steps and rounds the step it prints (1K: 1,000-1,999), so each line's
    step is the progress bar's last count before it, up to the next multiple of ``every``
    (the bar redraws at most ten times a second and may trail). A resumed run (appended to
    the log after its ``$ ... --resume=true`` line) counts its bar from its checkpoint, and
    replaces what the cut one logged after that checkpoint. A log with no progress bar counts
    the lines (steps ``every``, ``2 every``, ...)."""
    if not log.is_file():
        return []
    curve: list[tuple[int, float]] = []
    offset, count, last = 0, None, 0
    for m in _LOG_EVENT.finditer(log.read_text(errors="replace")):
        if m["command"] is not None:  # a (re)start: its bar counts from its checkpoint
            resumed = "--resume=true" in m["command"] and _CHECKPOINT.search(m["command"])
            offset = int(resumed[1]) if resumed else 0
            count, last = None, offset
        elif m["count"] is not None:
            count = int(m["count"])
        else:
            if count is None:
                step = last + every
            else:
                step = offset + max(every, -(-count // every) * every)
            while curve and curve[-1][0] >= step:  # a resumed run: its steps again
                curve.pop()
            curve.append((step, float(m["loss"])))
            last = step
    return curve
