"""``python -m beavr_sim.datasets generate``: demonstrations from synthesized VR traces.

Per episode: the task's scripted expert drives a synthetic operator's hands (the inverse of the
operator mapping and a human hand model, with tracking noise and dropouts; see
:mod:`beavr_sim.synthetic.trace`), the frames are saved as a VR trace, and the trace is replayed
through the full teleop pipeline (validator, operator, twin) while the recorder writes LeRobot
frames. The data is therefore what a VR operator's session produces, not expert actions. The
traces are kept in ``<out>/beavr_traces/`` so every episode can be replayed or re-recorded.

Seeds: episodes are tried with seeds ``seed``, ``seed + 1``, ... in order; a seed whose
synthesized episode fails is skipped (unless ``keep_failed``) until ``episodes`` are written,
or given up after ``5 * episodes + 10`` failures.

Into an existing dataset (a re-run): the run resumes. A seed whose episode of this task and
embodiment is already in the dataset (its ``meta/beavr_episodes.jsonl``) counts as written and
is not run again, so ``--episodes 2 --seed 0`` twice leaves seeds 0 and 1 once each, and a run
stopped half-way completes its seeds. ``overwrite`` starts anew instead. Which of the two (or
a new dataset) is said on stderr before the first episode, and in the summary's ``mode``.

Beyond one process (``scale``): every seed is a job that writes a shard of its own (see
:mod:`beavr_sim.datasets.shards`) in local worker processes or as a Ray task; the jobs are
handed out in seed order, no more at a time than there are workers and never more than could
still be needed (as if every running one succeeds), and the outcomes are read in seed order
with the serial rules above. The shards of the seeds a serial run would have written are then
merged in seed order: the same episodes, frames and stats as a serial run with the same seeds.
Shards live in ``<out>.shards/`` until merged; a run stopped before the merge resumes from the
finished ones when started again with the same options.

With a ``source`` (``python -m beavr_sim.datasets augment``) a seed's episode is made from a
recorded source episode instead of the expert (:mod:`beavr_sim.datasets.augment`); seeds,
workers, resume and merge are the same, and failures are counted by reason.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import sys
import tarfile
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import gymnasium as gym
from tqdm import tqdm

from beavr_sim.datasets.features import RecordingConfig, lerobot_features
from beavr_sim.datasets.quiet import quiet_dataset_writes
from beavr_sim.datasets.recorder import EpisodeRecorder, run_recorded_episode
from beavr_sim.datasets.resume import plan_output
from beavr_sim.datasets.save_journal import undo_interrupted_save
from beavr_sim.datasets.shards import TRACES, Shard, finish_interrupted_swap, merge_shards
from beavr_sim.datasets.writer import EpisodeWriter, dataset_exists
from beavr_sim.experts.base import check_expert_embodiment
from beavr_sim.scaling.executors import ScaleConfig, make_executor
from beavr_sim.tasks.registry import canonical_task_name

#: Test hook: ``SEED:MARKER`` makes the worker recording ``SEED`` exit abruptly (``os._exit``)
#: a few ticks into the recording, once: the first attempt creates the file ``MARKER``.
CRASH_ONCE_ENV = "BEAVR_SIM_CRASH_ONCE"
#: Ticks into the recording at which :data:`CRASH_ONCE_ENV` strikes.
CRASH_AFTER_TICKS = 10


@dataclass
class GenerateSummary:
    task: str
    embodiment: str
    out: str
    repo_id: str
    episodes_requested: int
    episodes_written: int
    successes: int
    failures: int
    seeds_failed: list[int] = field(default_factory=list)
    frames: int = 0
    wall_s: float = 0.0
    backend: str = "inline"
    workers: int = 1
    retried: int = 0
    #: ``new`` (no dataset at ``out``), ``resume`` (episodes appended; seeds already there
    #: skipped) or ``overwrite`` (the dataset at ``out`` replaced).
    mode: str = "new"
    #: Seeds of this run already in the dataset: not run again, not in ``episodes_written``.
    seeds_skipped: list[int] = field(default_factory=list)
    #: Failed episodes per reason (augmentation: the checker's unmet condition, ...).
    failure_reasons: dict[str, int] = field(default_factory=dict)
    #: The source dataset of an augmentation run ("" for expert demonstrations).
    source: str = ""


@dataclass(frozen=True)
class EpisodeJob:
    """One seed's work for a worker: synthesize, replay, record into the shard at ``shard``."""

    task: str
    embodiment: str
    seed: int
    config: RecordingConfig
    repo_id: str
    keep_failed: bool
    shard: str
    features: dict
    source: str = ""  # a source dataset to augment ("": the expert's synthesized trace)
    camera_poses: str = ""  # a --camera-poses file placing twin cameras ("": none)


@dataclass(frozen=True)
class EpisodeOutcome:
    seed: int
    synth_ok: bool
    written: bool
    frames: int
    reason: str = ""  # why the episode failed ("" when it did not)


def _crash_hook(seed: int):
    """The listener of :data:`CRASH_ONCE_ENV` for ``seed``, or None."""
    spec = os.environ.get(CRASH_ONCE_ENV, "")
    target, _, marker = spec.partition(":")
    if not spec or int(target) != seed or not marker or Path(marker).exists():
        return None
    ticks = [0]

    def listener(tick) -> None:
        ticks[0] += 1
        if ticks[0] == CRASH_AFTER_TICKS:
            Path(marker).touch()
            os._exit(17)

    return listener


def run_episode(
    task: str,
    seed: int,
    embodiment: str,
    config: RecordingConfig,
    keep_failed: bool,
    writer: EpisodeWriter | None,
    trace_dir: Path,
    make_writer=None,
    source: str = "",
    camera_poses: str = "",
) -> EpisodeOutcome:
    """One seed: synthesize its trace, and if kept replay it into ``writer`` (or into
    ``make_writer()``, called only when there is something to write), in a twin whose cameras
    ``camera_poses`` places (as teleop's ``--camera-poses``). With a ``source``: the seed's
    episode augmented from it (:func:`beavr_sim.datasets.augment.episode.augment_episode`)."""
    if source:
        from beavr_sim.datasets.augment.episode import augment_episode  # local: heavy

        done = augment_episode(
            source, task, seed, embodiment, config, keep_failed, writer, make_writer
        )
        return EpisodeOutcome(seed, done.success, done.written, done.frames, done.reason)
    from beavr_sim.synthetic.trace import quantize, synthesize, write_trace  # local: heavy (mujoco)
    from beavr_sim.teleop.session import (  # local: heavy (the pipeline: mink, scipy)
        SessionOptions,
        build_loop,
    )

    result = synthesize(task, seed, embodiment, quantize=quantize)
    ok = bool(result.summary.success)
    if not (ok or keep_failed):
        return EpisodeOutcome(seed, ok, False, 0)
    trace = write_trace(trace_dir / f"{task.lower()}_seed{seed:05d}.mcap", result)
    options = SessionOptions(
        task=task, source="trace", trace=trace, viser=False, headless=True, progress=False,
        camera_poses=camera_poses or None,
    )  # fmt: skip
    loop = build_loop(options)
    if writer is None:
        writer = make_writer()
    recorder = EpisodeRecorder(writer, loop.twin.env, config)
    crash = _crash_hook(seed)
    if crash is not None:
        loop.listeners.append(crash)
    try:
        replayed = run_recorded_episode(loop, recorder, config)
        written = recorder.end(
            keep=replayed.success or keep_failed,
            success=bool(replayed.success),
            seed=seed,
            source=f"synth trace {trace.name}",
        )
    finally:
        recorder.close()
        loop.twin.env.close()
    return EpisodeOutcome(seed, ok, bool(written), recorder.frames if written else 0)


def _features(task: str, embodiment: str, config: RecordingConfig) -> dict[str, dict]:

    probe = gym.make(f"beavr_sim/{task}-v0", embodiment=embodiment).unwrapped
    try:
        if int(round(probe.control_hz)) != config.fps:
            raise ValueError(f"fps must equal the env's control rate ({probe.control_hz:g} Hz)")
        return lerobot_features(probe.embodiment, config, probe.environment_state_names)
    finally:
        probe.close()


def run_episode_job(job: EpisodeJob) -> EpisodeOutcome:
    """Worker entry: the seed's shard from scratch (a retry wipes the previous attempt);
    ``outcome.json`` is written last, so a shard without it is unfinished."""
    quiet_dataset_writes()
    shard = Path(job.shard)
    if shard.exists():
        shutil.rmtree(shard)
    shard.mkdir(parents=True)
    root = Shard(shard).dataset

    def make_writer() -> EpisodeWriter:
        return EpisodeWriter(
            root,
            job.repo_id,
            job.features,
            job.config.fps,
            robot_type=job.embodiment,
            use_videos=job.config.use_videos,
        )

    holder: list[EpisodeWriter] = []

    def once() -> EpisodeWriter:
        holder.append(make_writer())
        return holder[0]

    try:
        outcome = run_episode(
            job.task,
            job.seed,
            job.embodiment,
            job.config,
            job.keep_failed,
            None,
            shard / TRACES,
            make_writer=once,
            source=job.source,
            camera_poses=job.camera_poses,
        )
    finally:
        for writer in holder:
            writer.close()
    (shard / "outcome.json").write_text(json.dumps(asdict(outcome)))
    return outcome


def run_episode_job_packed(job: EpisodeJob) -> tuple[EpisodeOutcome, bytes]:
    """Ray entry: the shard in a private temporary folder, returned as a tar archive (a
    cluster's nodes need not share a filesystem with the driver)."""
    with tempfile.TemporaryDirectory(prefix="beavr_shard_") as tmp:
        local = replace(job, shard=f"{tmp}/shard")
        outcome = run_episode_job(local)
        buffer = io.BytesIO()
        with tarfile.open(fileobj=buffer, mode="w") as tar:
            tar.add(local.shard, arcname=".")
        return outcome, buffer.getvalue()


def _unpack(data: bytes, shard: Path) -> None:
    if shard.exists():
        shutil.rmtree(shard)
    shard.mkdir(parents=True)
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as tar:
        tar.extractall(shard, filter="data")


@dataclass
class _SerialRules:
    """The serial run's bookkeeping over outcomes taken in seed order."""

    episodes: int
    written: int = 0
    successes: int = 0
    failures: int = 0
    frames: int = 0
    seeds_failed: list[int] = field(default_factory=list)
    reasons: dict[str, int] = field(default_factory=dict)
    used: list[int] = field(default_factory=list)  # seeds the serial run would have tried
    skipped: list[int] = field(default_factory=list)  # seeds already in the dataset
    gave_up: bool = False

    @property
    def done(self) -> bool:
        return self.written >= self.episodes or self.gave_up

    def take(self, outcome: EpisodeOutcome) -> None:
        self.used.append(outcome.seed)
        self.successes += int(outcome.synth_ok)
        self.failures += int(not outcome.synth_ok)
        if not outcome.synth_ok:
            self.seeds_failed.append(outcome.seed)
            reason = outcome.reason or "expert failed"
            self.reasons[reason] = self.reasons.get(reason, 0) + 1
        if outcome.written:
            self.written += 1
            self.frames += outcome.frames
        if self.failures > 5 * self.episodes + 10:
            self.gave_up = True

    def skip(self, seed: int) -> None:
        """A seed whose episode is already in the dataset: written, by an earlier run."""
        self.skipped.append(seed)
        self.written += 1


def generate(
    task: str,
    episodes: int,
    seed: int,
    out: Path,
    repo_id: str | None = None,
    embodiment: str = "xarm7_leap_right",
    config: RecordingConfig | None = None,
    keep_failed: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    scale: ScaleConfig | None = None,
    source: str | Path = "",
    camera_poses: str | Path | None = None,
) -> GenerateSummary:
    """``episodes`` demonstrations into the LeRobot dataset at ``out`` (resumed if it holds
    one: seeds already there are skipped; replaced with ``overwrite``). ``scale``: None or one
    local worker writes in this process, episode by episode; otherwise see the module
    docstring. ``source``: augment that recorded dataset instead of running the expert.
    ``camera_poses``: a file placing twin cameras (``--camera-poses``; ``config.cameras`` may
    name them); read by each worker, so on a cluster it must be at that path on every node."""
    task = canonical_task_name(task)
    source = str(Path(source).resolve()) if source else ""
    poses = str(Path(camera_poses).resolve()) if camera_poses else ""
    if poses and source:
        raise ValueError("--camera-poses places the expert's twin cameras, not augment's")
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    config = config or RecordingConfig()
    out = Path(out)
    repo_id = repo_id or f"beavr_sim/{task.lower()}"
    if not source:  # the scripted experts make the demonstrations
        check_expert_embodiment(embodiment)
    if finish_interrupted_swap(out):  # before counting what is there
        print(f"{out}: finished the merge a killed run left half swapped in", file=sys.stderr)
    undone = undo_interrupted_save(out, warn=False)
    if undone is not None:
        print(undone.describe(), file=sys.stderr)
    plan = plan_output(out, task, embodiment, overwrite)
    print(plan.describe(out, task, embodiment), file=sys.stderr)
    quiet_dataset_writes()
    if scale is None or scale.in_process:
        summary = _generate_serial(
            task, episodes, seed, out, repo_id, embodiment, config, keep_failed, plan, progress,
            source, poses,
        )  # fmt: skip
    else:
        summary = _generate_parallel(
            task, episodes, seed, out, repo_id, embodiment, config, keep_failed, plan, progress,
            scale, source, poses,
        )  # fmt: skip
    summary.mode = plan.mode
    summary.source = source
    return summary


def _generate_serial(
    task, episodes, seed, out, repo_id, embodiment, config, keep_failed, plan, progress, source,
    poses,
) -> GenerateSummary:  # fmt: skip
    features = _features(task, embodiment, config)
    writer = EpisodeWriter(
        out,
        repo_id,
        features,
        config.fps,
        robot_type=embodiment,
        use_videos=config.use_videos,
        overwrite=plan.mode == "overwrite",
    )
    summary = GenerateSummary(task, embodiment, str(out), repo_id, episodes, 0, 0, 0)
    rules = _SerialRules(episodes)
    start = time.perf_counter()
    bar = tqdm(total=episodes, desc=_bar_label(task, source), unit="ep", disable=not progress)
    episode_seed = seed
    try:
        while not rules.done:
            if episode_seed in plan.seeds_there:
                rules.skip(episode_seed)
                bar.update(1)
                episode_seed += 1
                continue
            outcome = run_episode(
                task, episode_seed, embodiment, config, keep_failed, writer, out / "beavr_traces",
                source=source, camera_poses=poses,
            )  # fmt: skip
            rules.take(outcome)
            bar.update(int(outcome.written))
            bar.set_postfix(ok=rules.successes, failed=rules.failures)
            episode_seed += 1
    finally:
        bar.close()
        writer.close()
    if rules.gave_up:
        print(f"giving up: {rules.failures} failed episodes", file=sys.stderr)
    _fill(summary, rules)
    summary.wall_s = round(time.perf_counter() - start, 2)
    return summary


def _bar_label(task: str, source: str) -> str:
    return f"{task} {'augmented' if source else 'demos'}"


def _fill(summary: GenerateSummary, rules: _SerialRules) -> None:
    summary.episodes_written = rules.written - len(rules.skipped)
    summary.seeds_skipped = list(rules.skipped)
    summary.successes = rules.successes
    summary.failures = rules.failures
    summary.seeds_failed = list(rules.seeds_failed)
    summary.failure_reasons = dict(rules.reasons)
    summary.frames = rules.frames


def staging_dir(out: Path) -> Path:
    """Where the shards of a parallel run into ``out`` wait for the merge."""
    return out.with_name(out.name + ".shards")


def _preload_merge() -> threading.Thread:
    """Import what the merge needs (LeRobot, torch: seconds) on a thread of its own."""

    def load() -> None:
        try:
            import lerobot.datasets.aggregate  # noqa: F401
        except ImportError:  # the merge itself says what is missing
            pass

    thread = threading.Thread(target=load, name="preload-merge", daemon=True)
    thread.start()
    return thread


def _generate_parallel(
    task, episodes, seed, out, repo_id, embodiment, config, keep_failed, plan, progress, scale,
    source, poses,
) -> GenerateSummary:  # fmt: skip
    features = _features(task, embodiment, config)  # validates fps before any worker starts
    staging = staging_dir(out)
    there = plan.seeds_there
    if plan.overwrite:  # a fresh start: no dataset, no shards of an earlier run
        for path in (out, staging):
            if path.exists():
                shutil.rmtree(path)
    if dataset_exists(out):
        EpisodeWriter(out, repo_id, features, config.fps, embodiment).close()  # compatible?
    elif out.exists() and any(out.iterdir()):
        raise FileExistsError(
            f"{out} exists and is not a LeRobot dataset; pick a new folder or pass overwrite"
        )
    manifest = {
        "task": task,
        "embodiment": embodiment,
        "repo_id": repo_id,
        "keep_failed": keep_failed,
        "config": asdict(config),
        "source": source,
        **({"camera_poses": poses} if poses else {}),  # (a run without: as before)
    }
    outcomes = _resume(staging, manifest)
    staging.mkdir(parents=True, exist_ok=True)
    (staging / "job.json").write_text(json.dumps(manifest, sort_keys=True))

    def shard_of(s: int) -> Path:
        return staging / f"seed{s:06d}"

    summary = GenerateSummary(task, embodiment, str(out), repo_id, episodes, 0, 0, 0)
    summary.backend = scale.backend
    start = time.perf_counter()
    ray = scale.ray
    function = "beavr_sim.synthetic.generate:" + (
        "run_episode_job_packed" if ray else "run_episode_job"
    )
    env = {CRASH_ONCE_ENV: os.environ[CRASH_ONCE_ENV]} if CRASH_ONCE_ENV in os.environ else {}
    executor = make_executor(function, scale, env=env)
    summary.workers = executor.capacity
    bar = tqdm(total=episodes, desc=_bar_label(task, source), unit="ep", disable=not progress)
    running: set[int] = set()
    next_seed = seed

    def serial_view() -> _SerialRules:
        rules = _SerialRules(episodes)
        s = seed
        while not rules.done and (s in there or s in outcomes):
            if s in there:
                rules.skip(s)
            else:
                rules.take(outcomes[s])
            s += 1
        return rules

    limit = 5 * episodes + 10
    # LeRobot (and torch) for the merge load on a thread while the workers run: seconds of
    # imports that would otherwise come after the last episode.
    preload = _preload_merge()
    retired = False
    tried = [0, 0]  # written, synthesis failures among the seeds below next_seed with outcomes

    def count(outcome: EpisodeOutcome) -> None:
        tried[0] += int(outcome.written)
        tried[1] += int(not outcome.synth_ok)

    try:
        while True:
            rules = serial_view()
            if rules.done:
                break
            # Hand out seeds in order while they could still be needed.
            while (
                len(running) < executor.capacity
                and tried[0] + len(running) < episodes
                and tried[1] <= limit
            ):
                if next_seed in there:  # in the dataset already
                    tried[0] += 1
                elif next_seed in outcomes:  # finished by an earlier, resumed run
                    count(outcomes[next_seed])
                else:
                    job = EpisodeJob(
                        task, embodiment, next_seed, config, repo_id, keep_failed,
                        str(shard_of(next_seed)), features, source, poses,
                    )  # fmt: skip
                    executor.submit(next_seed, job)
                    running.add(next_seed)
                next_seed += 1
            if not running:  # every seed handed out has its outcome: the next pass decides
                continue
            if len(running) < executor.capacity and not retired:
                # The last episodes run: no more is coming for an idle worker. Let it go (its
                # core is free for the others and for the merge's imports).
                executor.retire_idle()
                retired = True
            done_seed, result = executor.next_result()
            running.discard(done_seed)
            if ray:
                outcome, data = result
                _unpack(data, shard_of(done_seed))  # outcome.json included
            else:
                outcome = result
            outcomes[done_seed] = outcome
            count(outcome)
            bar.update(int(outcome.written))
            bar.set_postfix(ok=tried[0], failed=tried[1])
        bar.update(len(rules.skipped))
        bar.close()
        executor.retire_idle()  # all idle now: they exit while the shards are merged
        if rules.gave_up:
            print(f"giving up: {rules.failures} failed episodes", file=sys.stderr)
        preload.join()
        shards = [Shard(shard_of(s)) for s in rules.used]
        if not any(s.episodes for s in shards) and not dataset_exists(out):
            EpisodeWriter(out, repo_id, features, config.fps, embodiment, config.use_videos).close()
        merge_shards(shards, out, repo_id)
    finally:
        summary.retried = executor.retried
        executor.close()
        bar.close()
    (staging / "job.json").unlink()  # merged: these shards must never be resumed again
    shutil.rmtree(staging)
    _fill(summary, rules)
    summary.wall_s = round(time.perf_counter() - start, 2)
    return summary


def _resume(staging: Path, manifest: dict) -> dict[int, EpisodeOutcome]:
    """The finished shards of an earlier run with the same options (else a clean slate)."""
    outcomes: dict[int, EpisodeOutcome] = {}
    job_file = staging / "job.json"
    if job_file.is_file() and json.loads(job_file.read_text()) == json.loads(
        json.dumps(manifest, sort_keys=True)
    ):
        for done in staging.glob("seed*/outcome.json"):
            outcome = EpisodeOutcome(**json.loads(done.read_text()))
            outcomes[outcome.seed] = outcome
    elif staging.exists():
        shutil.rmtree(staging)
    return outcomes
