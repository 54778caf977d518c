"""Every shell command in README.md and docs/*.md, run as written on an offline machine.

The commands are read from the documents' ``bash`` blocks (continuation lines joined, comments
and ``[optional]`` parts left out). Each one matches exactly one entry of :data:`SPECS`, which
says how it is run: ``run`` (in a scratch folder holding ``.venv`` and ``assets`` links, so the
text runs unchanged) with tiny sizes, counts and steps substituted and, for a live session, an
end (``--max-seconds``, ``--seconds``, ``--teleop_time_s``) appended; or ``not run`` with the
reason (a real rig, a Ray cluster, placeholder paths, minutes of work, covered by another
test). A command that no entry matches, or an entry that no command matches, fails the test:
a changed document must be looked at again.

Offline: ``HF_HUB_OFFLINE=1``, empty ``TORCH_HOME`` / ``HF_HOME`` caches, and a
``sitecustomize`` in every Python process that refuses connections to anything but this
machine, so a command that would download (torchvision's ImageNet weights, a Hub file) fails.

Runtime: a few minutes on the 2-core dev machine (24 commands). The README's first
``datasets generate`` runs on one worker (``--workers 1``: on one worker per core, each starting
LeRobot's video-encoding processes, it took 100 s); its ``--workers 8`` command runs on two.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = (ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")))
VENV = Path(sys.executable).parent.parent


#: How a command starts, in a code block of no language (the rest of such a block is output).
COMMAND_START = re.compile(r"^(python -m |\.venv/bin/|make |[A-Z_]+=\S+ \.venv/bin/|lerobot-)")


def extract_commands(text: str) -> list[str]:
    """The shell commands of a Markdown text: every line of its ``bash`` / ``sh`` blocks and
    the lines of its blocks of no language that start as a command (:data:`COMMAND_START`),
    continuation lines joined, comments left out, one command per entry."""
    commands = []
    for language, block in re.findall(r"```([a-z]*)\n(.*?)```", text, re.S):
        if language not in ("", "bash", "sh", "shell"):
            continue
        for line in re.sub(r"\\\n\s*", " ", block).splitlines():
            line = re.sub(r"\s+#.*$", "", line.strip())  # a trailing comment
            line = re.sub(r"\s+", " ", line)
            if not line or line.startswith("#"):
                continue
            if language or COMMAND_START.match(line):
                commands.append(line)
    return commands


def document_commands() -> list[tuple[str, str]]:
    """(document name, command) for every command of :data:`DOCUMENTS`, in order."""
    return [
        (str(doc.relative_to(ROOT)), command)
        for doc in DOCUMENTS
        for command in extract_commands(doc.read_text())
    ]


@dataclass(frozen=True)
class Spec:
    """How one documented command is checked (see the module docstring).

    ``match``: a regular expression the command matches (``re.search``); ``why``: for a
    command not run, the reason; ``tiny``: (regex, replacement) pairs applied in order;
    ``extra``: arguments appended; ``check``: what the run must leave behind, a path relative
    to the scratch folder (a file or folder).
    """

    match: str
    why: str = ""
    tiny: tuple[tuple[str, str], ...] = ()
    extra: str = ""
    check: str = ""
    timeout_s: float = 300.0

    @property
    def runs(self) -> bool:
        return not self.why


TRAIN_TINY = (
    "--steps=2 --batch_size=2 --num_workers=0 --save_freq=2 --log_freq=1 "
    "--policy.chunk_size=10 --policy.n_action_steps=10 --policy.dim_model=32 "
    "--policy.dim_feedforward=64 --policy.n_encoder_layers=1 --policy.n_decoder_layers=1"
)
IMAGES_TINY = (
    (r"--env\.image_height=96", "--env.image_height=24"),
    (r"--env\.image_width=128", "--env.image_width=32"),
)
LIVE = "--max-seconds 1 --no-viser"  # the browser view would bind 8080, maybe held by another

SPECS: tuple[Spec, ...] = (
    Spec(r"^make demo", why="builds .venv and replays until Ctrl-C; its replay is run below"),
    Spec(r"^make test", why="the whole test suite"),
    Spec(r"^make traces", why="re-synthesizes all bundled traces (minutes); see traces synth"),
    Spec(r"teleop --task pour --headset-host 0\.0\.0\.0$", extra=LIVE),
    Spec(r"teleop --task pour --source trace --no-viser --summary-json", extra="--max-seconds 1",
         check="out.json"),
    Spec(r"teleop --task pour --source webxr", extra=f"{LIVE} --webxr-port 0"),
    Spec(r"teleop --task pour --source trace --mirror-hardware --hardware-config emulated",
         extra="--max-seconds 1"),
    Spec(r"--hardware-config rig\.toml", why="a real rig: its rig.toml names real devices"),
    Spec(r"datasets generate .*--camera-poses rig\.toml",
         why="rig.toml: a placeholder (test_twin_cameras.py generates with placed cameras)"),
    Spec(r"teleop --source webxr --camera-stream-hz 5",
         why="a live WebXR session streaming the twin's front camera; test_cameras.py's "
             "test_a_session_without_cameras_streams_the_twins_camera runs the same path"),
    Spec(r"teleop --record data/rec --camera ",
         why="real cameras (a webcam, a LAN ZMQ server, a RealSense); test_cameras.py runs the "
             "same path through LeRobot's OpenCV (a video file) and ZMQ cameras"),
    Spec(r"beavr_sim\.cameras (board|calibrate) --board board\.toml",
         why="a printed board and a real camera's images (placeholders board.toml, front_*.png); "
             "test_camera_calibration.py runs both commands on a board the twin renders"),
    Spec(r"beavr_sim\.robots check path/to/robot\.toml",
         why="path/to/robot.toml: a placeholder; test_robot_file.py runs the check on a robot file "
             "and test_robot_file_franka.py on the Franka example"),
    Spec(r"--embodiment path/to/robot\.toml",
         why="path/to/robot.toml: a placeholder; test_robot_file_franka.py replays the bundled "
             "PickupBox trace through teleop with the Franka example"),
    Spec(r"traces info assets/traces/pour\.mcap"),
    Spec(r"traces record --out my\.mcap", extra="--seconds 0.5", check="my.mcap"),
    Spec(r"traces synth --task pour --seed 0 --out pour\.mcap", extra="--no-verify",
         check="pour.mcap"),
    Spec(r"traces recover cut\.mcap --out fixed\.mcap", check="fixed.mcap"),
    Spec(r"teleop --task pickup_box --record",
         why="a live recording: episodes start on Enter at a terminal, the browser view or a "
         "pinch, so it waits for a person (teleop --record from a trace: test_datasets.py)"),
    Spec(r"datasets generate --task pickup_box --episodes 50 --seed 0",
         tiny=((r"--episodes 50", "--episodes 1"), (r"96x128", "24x32")), extra="--workers 1",
         check="data/pickup_box"),
    Spec(r"lerobot-train .*--output_dir=outputs/act_pickup_box$", extra=TRAIN_TINY,
         check="outputs/act_pickup_box/checkpoints/last/pretrained_model/model.safetensors"),
    Spec(r"beavr_sim\.eval --policy outputs/act_pickup_box",
         tiny=((r"--episodes 20", "--episodes 1"),), extra="--max-seconds 0.3 --quiet"),
    Spec(r"datasets generate --task pickup_box --episodes 200 --out data/pickup --workers 8$",
         tiny=((r"--episodes 200", "--episodes 1"), (r"--workers 8", "--workers 2")),
         extra="--image-size 24x32 --cameras front", check="data/pickup"),
    Spec(r"generate .*--ray", why="needs a Ray cluster at HEAD:6379 (Ray: test_scaling.py)"),
    Spec(r"beavr_sim\.eval --policy runs/",
         why="placeholder policy folders (runs/...) and a Ray cluster or 8 workers; the sweep "
         "on workers: test_scaling.py"),
    Spec(r"beavr_sim\.eval --policy \.\.\.", why="placeholders (...)"),
    Spec(r"lerobot-eval --policy\.path=outputs/act_pickup_box",
         tiny=((r"--eval\.n_episodes=20", "--eval.n_episodes=1"),
               (r"--eval\.batch_size=4", "--eval.batch_size=1"), *IMAGES_TINY),
         extra="--env.episode_length=3 --output_dir=outputs/eval_pickup_box",
         check="outputs/eval_pickup_box/eval_info.json"),
    Spec(r"lerobot-train .*--env_eval_freq=5000",
         tiny=((r"--env_eval_freq=5000", "--env_eval_freq=2"),
               (r"--eval\.n_episodes=10", "--eval.n_episodes=1"), *IMAGES_TINY),
         extra=f"{TRAIN_TINY} --env.episode_length=3 --eval.batch_size=1",
         check="outputs/act_pickup_box_env/checkpoints/last/pretrained_model"),
    Spec(r"lerobot-teleoperate", extra="--teleop_time_s=1"),
    Spec(r"lerobot-record .*--robot\.cameras=",
         why="a real camera (a webcam); test_cameras.py runs lerobot-record's main with "
             "--robot.cameras on a ZMQ image server"),
    Spec(r"lerobot-record (?!.*--robot\.cameras=)", tiny=((r"--dataset\.episode_time_s=20", "--dataset.episode_time_s=1"),),
         check="data/pickup_box_lr/meta/info.json"),
    Spec(r"lerobot-replay"),
    Spec(r"beavr_sim\.experts --task pour --episodes 50",
         tiny=((r"--episodes 50", "--episodes 1"),)),
    # docs/benchmarks.md
    Spec(r"bench latency --config 1 --seconds 10", tiny=((r"--seconds 10", "--seconds 1"),),
         check="/tmp/latplots1"),
    Spec(r"bench latency (--config [234]|--sweep)",
         why="the config-1 command with another --config, --layout or --sweep: 10 s and more "
         "each (configurations: test_bench_latency.py)"),
    Spec(r"bench tracking$", why="a minute of replays (test_bench_tracking.py runs 200 ticks)"),
    Spec(r"bench\.webxr", why="needs chromium and playwright (make sysdeps; test_webxr_browser.py)"),
    Spec(r"datasets augment --source (SRC|data/pick_few)",
         why="placeholder source datasets (SRC, data/...); test_augment.py augments a source it "
         "records itself"),
    # docs/hardware.md
    Spec(r"--task pick_place --embodiment rx1 .*--hardware-config emulated$",
         extra="--max-seconds 1"),
    Spec(r"hardware\.guard --embodiment xarm7_leap_right --qpos-file q\.npy$"),
    Spec(r"hardware\.guard --qpos-file q\.npy --stream --hz 30$"),
    # docs/scaling.md
    Spec(r"datasets generate --task pickup_box --episodes 200 --out data/pickup --image-size",
         why="the README's --workers command with --image-size 96x128 (run above at 24x32)"),
)  # fmt: skip


def spec_of(command: str) -> Spec:
    found = [s for s in SPECS if re.search(s.match, command)]
    assert len(found) == 1, f"{command!r} matches {len(found)} entries of SPECS: {found}"
    return found[0]


def test_every_documented_command_has_exactly_one_entry():
    commands = document_commands()
    assert len(commands) > 30, "the documents' bash blocks were not found"
    for doc, command in commands:
        assert [s for s in SPECS if re.search(s.match, command)], (
            f"{doc}: {command!r} has no entry in SPECS: say how it is run (or why not)"
        )
        spec_of(command)
    for spec in SPECS:
        assert any(re.search(spec.match, c) for _, c in commands), f"stale entry: {spec}"


def tiny_command(spec: Spec, command: str) -> str:
    command = re.sub(r"\s+\[--[^\]]*\]", "", command)  # [--optional parts], not '[a, b]' values
    for pattern, replacement in spec.tiny:
        changed = re.sub(pattern, replacement, command)
        assert changed != command, f"{pattern!r} is not in {command!r}"
        command = changed
    return f"{command} {spec.extra}".strip()


SITECUSTOMIZE = '''
"""Test harness: no connection leaves this machine (an offline machine)."""
import ipaddress
import socket

_connect = socket.socket.connect
_connect_ex = socket.socket.connect_ex


def _local(address):
    if not isinstance(address, tuple):
        return True  # a unix socket
    host = address[0]
    if host in ("localhost", ""):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback or ipaddress.ip_address(host).is_unspecified
    except ValueError:
        return False


def connect(self, address):
    if not _local(address):
        raise OSError(101, f"offline test machine: no route to {address}")
    return _connect(self, address)


def connect_ex(self, address):
    if not _local(address):
        return 101
    return _connect_ex(self, address)


socket.socket.connect = connect
socket.socket.connect_ex = connect_ex
'''


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """A scratch folder as a fresh checkout would be after ``make``: ``.venv`` and ``assets``
    there; the environment of an offline machine with empty caches."""
    pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")
    work = tmp_path_factory.mktemp("readme")
    (work / ".venv").symlink_to(VENV)
    (work / "assets").symlink_to(ROOT / "assets")
    site = work / "_offline"
    site.mkdir()
    (site / "sitecustomize.py").write_text(SITECUSTOMIZE)
    # A truncated trace for `traces recover`; a joint-target file for the guard.
    data = (ROOT / "assets" / "traces" / "pour.mcap").read_bytes()
    (work / "cut.mcap").write_bytes(data[: len(data) // 2])
    import numpy as np

    from beavr_sim.hardware.guard import scene_guard

    home = scene_guard("xarm7_leap_right")[2]
    np.save(work / "q.npy", np.stack([home, home + 0.01]))
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)]),
        "MUJOCO_GL": "egl",
        "HF_HUB_OFFLINE": "1",
        "HF_DATASETS_OFFLINE": "1",
        "TORCH_HOME": str(work / "_cache" / "torch"),
        "HF_HOME": str(work / "_cache" / "hf"),
        "HF_LEROBOT_HOME": str(work / "_cache" / "lerobot"),
        "WANDB_MODE": "disabled",
        "PATH": os.pathsep.join([str(VENV / "bin"), os.environ.get("PATH", "")]),  # activated
    }
    return work, env


def _runs() -> list[tuple[str, str]]:
    """The commands run, each once (the docs repeat some of the README's), in order."""
    seen: set[str] = set()
    runs = []
    for doc, command in document_commands():
        found = [s for s in SPECS if re.search(s.match, command)]
        if len(found) != 1:
            continue  # test_every_documented_command_has_exactly_one_entry fails for it
        spec = found[0]
        if spec.runs and tiny_command(spec, command) not in seen:
            seen.add(tiny_command(spec, command))
            runs.append((doc, command))
    return runs


RUNS = _runs()


@pytest.mark.parametrize(("doc", "command"), RUNS, ids=[c[:60] for _, c in RUNS])
def test_documented_command_runs_offline(workspace, doc, command):
    """In document order (the later ones use what the earlier ones made)."""
    work, env = workspace
    spec = spec_of(command)
    line = tiny_command(spec, command)
    words = shlex.split(line)
    assignments = {}
    while words and re.match(r"^[A-Z_]+=", words[0]):  # VAR=value before the command
        name, _, value = words.pop(0).partition("=")
        assignments[name] = value
    done = subprocess.run(
        words,
        cwd=work,
        env={**env, **assignments},
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=spec.timeout_s,
    )
    assert done.returncode == 0, f"{doc}: {line}\n{done.stdout[-1500:]}\n{done.stderr[-3000:]}"
    if spec.check:
        assert (work / spec.check).exists(), f"{line} left no {spec.check}"
    if "--summary-json" in line:
        json.loads((work / "out.json").read_text())
