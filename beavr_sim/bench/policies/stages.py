"""The policy table's stages, each cached in the output folder under its configuration's key,
and the pipeline that chains them.

Stages, per task: demonstrations (``demos/<task>-<key>/``, a LeRobot dataset, resumed by the
generator itself), with ``augment`` the episodes generated from them and merged with them
(``augment/<task>-<key>/``: ``generated/dataset`` and the merged ``dataset``), per policy a training run (``train/<policy>-<task>-<key>/``: LeRobot's
``run/``, ``train.log``), the checkpoint choice (every saved checkpoint on the validation seeds,
sync; the most successes wins, the later step on a tie), every checkpoint's open-loop fit on
the first training episodes (``fit/<name>-<key>.json``, :mod:`beavr_sim.eval.fit`: a few
seconds each, it says whether the run learned its own data before a test does), its test
episodes (sync and think-act), and the scripted expert through the teleop pipeline on the test
seeds (the "human" row). Evaluations are ``eval/<name>-<key>.json``. A stage is finished when its
``stage.json`` (or its eval JSON) is written, last: a re-run skips it and reports it cached.

Each stage prints one line on stderr when it ends: what it did, wall and CPU time (this
process's and its children's), or that it was cached.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from beavr_sim.bench.policies import train as training
from beavr_sim.bench.policies.config import (
    HUB_POLICIES,
    NOT_RUN_OFFLINE,
    PRESETS,
    QUICK_PRESETS,
    TEST_SEED,
    VALIDATION_SEED,
    AugmentConfig,
    DemoConfig,
    EvalConfig,
    FitConfig,
    Protocol,
    TrainConfig,
    cache_key,
    file_hash,
)
from beavr_sim.scaling.executors import ScaleConfig

#: Name of a finished stage's marker file.
DONE = "stage.json"


class StageFailed(RuntimeError):
    """A stage could not produce its output (the message says which and why)."""


@dataclass(frozen=True)
class TableConfig:
    """What one table is (everything here is part of some stage's key)."""

    tasks: tuple[str, ...]
    policies: tuple[str, ...]
    protocol: Protocol
    quick: bool = False
    embodiment: str = "xarm7_leap_right"
    cameras: tuple[str, ...] = ()
    image_height: int = 96
    image_width: int = 128
    #: Training steps and steps between checkpoints (None: the preset's).
    steps: int | None = None
    save_freq: int | None = None
    #: Episode time limit of the policy evaluations (None: the env's).
    max_seconds: float | None = None
    #: Evaluation loops on the test seeds.
    modes: tuple[str, ...] = ("sync", "async")
    #: Episodes generated from the demonstrations (``datasets augment``) and trained on with
    #: them (0: the demonstrations alone).
    augment: int = 0
    #: Also the scripted expert through the teleop pipeline (the "human" row).
    expert_row: bool = True


@dataclass(frozen=True)
class RunOptions:
    """Where and how the stages run (never part of a cache key)."""

    out: Path
    device: str = "cpu"
    workers: int = 1
    resume: bool = False
    #: LeRobot's data-loading processes per training run (``--num_workers``).
    loader_workers: int = 0
    #: Torch device of the evaluation episodes (None: ``device``). On a GPU machine the CPU is
    #: often the faster choice: every evaluation stage starts fresh worker processes, and each
    #: would set up CUDA for a policy of a few million parameters.
    eval_device: str | None = None
    #: Continue a finished run of the same training configuration with fewer steps (ACT
    #: only: :data:`~beavr_sim.bench.policies.config.EXTENDABLE_POLICIES`) instead of
    #: starting from step 0.
    extend: bool = False


def _cpu_seconds() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _write_json(path: Path, data: dict) -> None:
    """Written whole or not at all (a cut run never leaves half a marker)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    partial.write_text(json.dumps(data, indent=2))
    os.replace(partial, path)


class Stages:
    """Runs cached stages, one progress line each, and keeps their records."""

    def __init__(self, total: int, echo: Callable[[str], None] | None = None):
        self.total = total
        self.records: list[dict] = []
        self._echo = echo or (lambda line: print(line, file=sys.stderr, flush=True))

    def run(self, stage: str, what: str, key: str, marker: Path, work: Callable[[], dict]) -> dict:
        """``work()``'s result, stored at ``marker``; read from there if it exists."""
        n = len(self.records) + 1
        if marker.is_file():
            result = json.loads(marker.read_text())
            self.records.append({"stage": stage, "what": what, "key": key, "cached": True,
                                 "wall_s": result.get("stage_wall_s", 0.0),
                                 "cpu_s": result.get("stage_cpu_s", 0.0)})  # fmt: skip
            self._echo(f"[{n}/{self.total}] {what}: cached ({marker})")
            return result
        wall, cpu = time.perf_counter(), _cpu_seconds()
        result = work()
        wall, cpu = time.perf_counter() - wall, _cpu_seconds() - cpu
        record = {"stage": stage, "what": what, "key": key, "cached": False,
                  "wall_s": round(wall, 2), "cpu_s": round(cpu, 2)}  # fmt: skip
        result = {**result, "stage_wall_s": record["wall_s"], "stage_cpu_s": record["cpu_s"]}
        _write_json(marker, result)
        self.records.append(record)
        self._echo(f"[{n}/{self.total}] {what}: {wall:.1f} s wall, {cpu:.1f} s CPU")
        return result

    def budget(self) -> dict:
        """Wall and CPU time of every stage (a cached one: when it ran), in total and per kind
        of stage, and of the stages this run ran."""
        by_stage: dict[str, dict] = {}
        for r in self.records:
            entry = by_stage.setdefault(r["stage"], {"wall_s": 0.0, "cpu_s": 0.0})
            entry["wall_s"] = round(entry["wall_s"] + r["wall_s"], 2)
            entry["cpu_s"] = round(entry["cpu_s"] + r["cpu_s"], 2)
        now = [r for r in self.records if not r["cached"]]
        return {
            "wall_s": round(sum(r["wall_s"] for r in self.records), 2),
            "cpu_s": round(sum(r["cpu_s"] for r in self.records), 2),
            "by_stage": by_stage,
            "stages_cached": len(self.records) - len(now),
            "this_run_wall_s": round(sum(r["wall_s"] for r in now), 2),
            "this_run_cpu_s": round(sum(r["cpu_s"] for r in now), 2),
        }


def demo_config(config: TableConfig, task: str) -> DemoConfig:
    return DemoConfig(
        task=task,
        episodes=config.protocol.demos,
        embodiment=config.embodiment,
        cameras=config.cameras,
        image_height=config.image_height,
        image_width=config.image_width,
    )


def train_config(config: TableConfig, policy: str, demos: DemoConfig) -> TrainConfig:
    preset = (QUICK_PRESETS if config.quick else PRESETS)[policy]
    steps = config.steps or preset.steps
    return TrainConfig(
        policy=policy,
        demos=demos,
        steps=steps,
        save_freq=min(config.save_freq or preset.save_freq, steps),
        batch_size=preset.batch_size,
        policy_flags=preset.flags,
        augmented=config.augment,
    )


def inputs(train: TrainConfig) -> str:
    """What a row's policy saw: its inputs, and the generated episodes it was trained on."""
    if not train.augmented:
        return train.demos.inputs
    return (
        f"{train.demos.inputs}; {train.demos.episodes} demos + {train.augmented} generated "
        "from them"
    )


def repo_id(demos: DemoConfig) -> str:
    return f"beavr_sim/{demos.task.lower()}"


def make_demos(demos: DemoConfig, stages: Stages, options: RunOptions) -> Path:
    """The demonstration dataset (generated, or resumed by the generator, or cached)."""
    from beavr_sim.datasets.features import RecordingConfig  # local: heavy (mujoco)
    from beavr_sim.datasets.resume import plan_output  # local: heavy (lerobot)
    from beavr_sim.synthetic.generate import generate  # local: heavy (mujoco, the pipeline)

    key = cache_key("demos", demos)
    root = options.out / "demos" / f"{demos.task}-{key}"

    def work() -> dict:
        recording = RecordingConfig(
            cameras=demos.cameras,
            image_height=demos.image_height,
            image_width=demos.image_width,
            hand_keypoints=False,
            environment_state=demos.environment_state,
        )
        summary = generate(
            demos.task,
            demos.episodes,
            demos.seed,
            root / "dataset",
            repo_id=repo_id(demos),
            embodiment=demos.embodiment,
            config=recording,
            progress=False,
            scale=ScaleConfig(workers=options.workers),
        )
        written = summary.episodes_written + len(summary.seeds_skipped)
        if written < demos.episodes:
            raise StageFailed(
                f"{demos.task}: only {written} of {demos.episodes} demonstrations succeeded "
                f"(failed seeds {summary.seeds_failed}); see {root}"
            )
        seeds = sorted(
            plan_output(root / "dataset", demos.task, demos.embodiment, False).seeds_there
        )
        if seeds[-1] >= TEST_SEED:
            raise StageFailed(
                f"{demos.task}: demonstration seeds reached {seeds[-1]}, into the test seeds"
            )
        return {"config": asdict(demos), "frames": summary.frames, "seeds": seeds}

    what = f"demos {demos.task}: {demos.episodes} from seed {demos.seed} ({demos.inputs})"
    stages.run("demos", what, key, root / DONE, work)
    return root / "dataset"


def make_augmented(
    augment: AugmentConfig, demos: Path, stages: Stages, options: RunOptions
) -> Path:
    """The demonstrations at ``demos`` and ``augment.episodes`` episodes generated from them
    (``datasets augment``: only the demonstrations drive them), merged into one dataset."""
    from beavr_sim.datasets.augment.source import open_source  # local: heavy (lerobot)
    from beavr_sim.datasets.shards import Shard, merge_shards  # local: heavy (lerobot)
    from beavr_sim.synthetic.generate import generate  # local: heavy (mujoco, the pipeline)

    key = cache_key("augment", augment)
    root = options.out / "augment" / f"{augment.source.task}-{key}"

    def work() -> dict:
        source = open_source(demos)
        summary = generate(
            source.task,
            augment.episodes,
            augment.seed,
            root / "generated" / "dataset",
            repo_id=repo_id(augment.source),
            embodiment=source.embodiment,
            config=source.recording_config(),
            progress=False,
            scale=ScaleConfig(workers=options.workers),
            source=source.root,
        )
        written = summary.episodes_written + len(summary.seeds_skipped)
        if written < augment.episodes:
            raise StageFailed(
                f"{source.task}: augmentation kept {written} of {augment.episodes} episodes "
                f"(failures by reason {summary.failure_reasons}); see {root}"
            )
        merged = root / "dataset"
        if merged.exists():  # a merge cut short: made again from its parts
            shutil.rmtree(merged)
        total = merge_shards(
            [Shard(demos.parent), Shard(root / "generated")], merged, repo_id(augment.source)
        )
        return {
            "config": asdict(augment),
            "kept": written,
            "tried": written + summary.failures,
            "failure_reasons": summary.failure_reasons,
            "episodes_merged": total,
        }

    what = (
        f"augment {augment.source.task}: {augment.episodes} from {augment.source.episodes} "
        f"demos, scenes from seed {augment.seed}"
    )
    stages.run("augment", what, key, root / DONE, work)
    return root / "dataset"


def train_policy(
    train: TrainConfig, dataset: Path, stages: Stages, options: RunOptions
) -> tuple[str, Path]:
    """(key, run folder) of the finished training run."""
    key = cache_key("train", train)
    stage = options.out / "train" / f"{train.policy}-{train.demos.task}-{key}"

    def work() -> dict:
        extended = None
        if options.extend and not training.saved_steps(stage / "run"):
            found = training.shorter_run(options.out / "train", train)
            if found is not None:
                source, steps = found
                print(f"extending {source} from step {steps} to {train.steps}", file=sys.stderr)
                training.extend_from(source, stage)
                extended = {"stage": str(source), "steps": steps}
        run = training.train(
            train,
            dataset,
            repo_id(train.demos),
            stage,
            options.device,
            options.resume or extended is not None,
            options.loader_workers,
        )
        return {
            "config": asdict(train),
            "device": options.device,
            "steps_saved": training.saved_steps(run),
            "loss": loss_curve(train, run),
            # Continued from that run's last checkpoint (LeRobot's resume), not from step 0.
            "extended_from": extended,
        }

    what = f"train {train.policy} on {train.demos.task}: {train.steps} steps"
    stages.run("train", what, key, stage / DONE, work)
    return key, stage / "run"


def evaluate(
    evaluation: EvalConfig, checkpoint: Path | None, stages: Stages, options: RunOptions, name: str
) -> dict:
    """One evaluation's summary (policy checkpoint, or the expert's row without one)."""
    key = cache_key("eval", evaluation)
    marker = options.out / "eval" / f"{name}-{key}.json"

    def work() -> dict:
        if evaluation.mode == "teleop":
            row = _expert_episodes(evaluation)
        else:
            from beavr_sim.eval.sweep import sweep  # local: heavy (mujoco, torch)

            row = sweep(
                [checkpoint],
                [evaluation.task],
                evaluation.embodiment,
                evaluation.episodes,
                evaluation.seed,
                scale=ScaleConfig(workers=options.workers),
                asynchronous=evaluation.mode == "async",
                max_seconds=evaluation.max_seconds,
                device=options.eval_device or options.device,
                progress=False,
            )["results"][0]
        return {"config": asdict(evaluation), **row}

    last = evaluation.seed + evaluation.episodes - 1
    what = f"eval {name} {evaluation.mode}, seeds {evaluation.seed}-{last}"
    return stages.run("eval", what, key, marker, work)


def fit(
    train: TrainConfig, key: str, run: Path, step: int, dataset: Path, stages: Stages,
    options: RunOptions,
) -> dict:  # fmt: skip
    """The open-loop fit of the checkpoint at ``step`` on the first training episodes
    (:data:`~beavr_sim.bench.policies.config.FIT_EPISODES`)."""
    config = FitConfig(train_key=key, step=step, weights=_weights(run, step))
    fit_key = cache_key("fit", config)
    name = f"{train.policy}-{train.demos.task}-step{step}"
    marker = options.out / "fit" / f"{name}-{fit_key}.json"

    def work() -> dict:
        from beavr_sim.datasets.writer import open_dataset  # local: heavy (LeRobot datasets)
        from beavr_sim.eval.fit import open_loop_fit  # local: heavy (torch)
        from beavr_sim.eval.policy import LoadedPolicy  # local: heavy (torch)

        data = open_dataset(dataset)
        episodes = tuple(e for e in config.episodes if e < data.meta.total_episodes)
        policy = LoadedPolicy(training.checkpoint(run, step), options.eval_device or options.device)
        return {"config": asdict(config), **open_loop_fit(policy, data, episodes).as_dict()}

    episodes = ", ".join(map(str, config.episodes))
    return stages.run("fit", f"fit {name} on training episodes {episodes}", fit_key, marker, work)


def _expert_episodes(evaluation: EvalConfig) -> dict:
    """The scripted expert driving synthetic VR hands through the teleop pipeline (operator,
    guard, twin), one episode per seed: the table's "human" row."""
    from beavr_sim.eval.runner import EpisodeResult, summarize  # local: heavy (mujoco)
    from beavr_sim.synthetic.trace import synthesize  # local: heavy (the pipeline)

    results = []
    for seed in range(evaluation.seed, evaluation.seed + evaluation.episodes):
        summary = synthesize(evaluation.task, seed, evaluation.embodiment).summary
        ticks = int(summary.ticks)
        results.append(EpisodeResult(seed, bool(summary.success), summary.duration_s, ticks))
    # (the control rate only matters to the think-act loop's jitter, not measured here)
    row = summarize(results, evaluation.task, evaluation.embodiment, "expert", False, 30.0)
    row["mode"] = "teleop"
    return row


def _weights(run: Path, step: int) -> str:
    return file_hash(training.checkpoint(run, step) / "model.safetensors")


def choose_checkpoint(
    config: TableConfig, train: TrainConfig, key: str, run: Path, dataset: Path, stages: Stages,
    options: RunOptions,
) -> tuple[int, list[dict], dict]:  # fmt: skip
    """The step whose checkpoint succeeds most on the validation seeds (sync; the later step
    on a tie), every checkpoint's validation summary with its open-loop fit (``fit``: mean
    absolute action error, ``fit_relative``: that over the recorded actions' spread), and the
    chosen checkpoint's fit summary."""
    validation, fits = [], {}
    for step in training.saved_steps(run):
        fitted = fits[step] = fit(train, key, run, step, dataset, stages, options)
        evaluation = EvalConfig(
            task=train.demos.task,
            embodiment=train.demos.embodiment,
            seed=VALIDATION_SEED,
            episodes=config.protocol.validation_episodes,
            mode="sync",
            train_key=key,
            step=step,
            weights=_weights(run, step),
            max_seconds=config.max_seconds,
        )
        name = f"{train.policy}-{train.demos.task}-step{step}-validation"
        row = evaluate(evaluation, training.checkpoint(run, step), stages, options, name)
        validation.append({"step": step, "successes": row["successes"],
                           "episodes": row["episodes"], "fit": fitted["mean_abs"],
                           "fit_relative": fitted["relative"]})  # fmt: skip
    best = max(validation, key=lambda v: (v["successes"], v["step"]))
    return best["step"], validation, fits[best["step"]]


def stage_count(config: TableConfig) -> int:
    """How many stages the table runs (for the ``[n/total]`` of the progress lines)."""
    total = 0
    for task in config.tasks:
        demos = demo_config(config, task)
        total += 1 + (1 if config.expert_row else 0) + (1 if config.augment else 0)
        for policy in config.policies:
            train = train_config(config, policy, demos)
            checkpoints = -(-train.steps // train.save_freq)  # every save_freq and the last
            total += 1 + 2 * checkpoints + len(config.modes)  # train, fits, validations, tests
    return total


def loss_curve(train: TrainConfig, run: Path) -> list[dict]:
    """``[{"step", "loss"}, ...]``: the training loss of the run at ``run`` as LeRobot logged
    it."""
    curve = training.loss_curve(run.parent / "train.log", training.log_freq(train))
    return [{"step": step, "loss": loss} for step, loss in curve]


def run_table(config: TableConfig, options: RunOptions, stages: Stages) -> dict:
    """Every stage of the table, in order; the table's JSON (rows, protocol, budget)."""
    rows: list[dict] = []
    validation_seeds = (VALIDATION_SEED, VALIDATION_SEED + config.protocol.validation_episodes - 1)
    test = dict(seed=TEST_SEED, episodes=config.protocol.test_episodes)
    for task in config.tasks:
        demos = demo_config(config, task)
        dataset = make_demos(demos, stages, options)
        if config.augment:
            dataset = make_augmented(AugmentConfig(demos, config.augment), dataset, stages, options)
        for policy in config.policies:
            train = train_config(config, policy, demos)
            key, run = train_policy(train, dataset, stages, options)
            step, validation, fitted = choose_checkpoint(
                config, train, key, run, dataset, stages, options
            )
            curve = loss_curve(train, run)
            for mode in config.modes:
                evaluation = EvalConfig(
                    task=task, embodiment=config.embodiment, mode=mode, train_key=key,
                    step=step, weights=_weights(run, step), max_seconds=config.max_seconds,
                    **test,
                )  # fmt: skip
                name = f"{policy}-{task}-step{step}-test"
                row = evaluate(evaluation, training.checkpoint(run, step), stages, options, name)
                rows.append(
                    _row(row, policy, inputs(train), mode)
                    | {
                        "demos": demos.episodes,
                        "augmented": train.augmented,
                        "train_steps": train.steps,
                        "checkpoint_step": step,
                        "chosen_on": f"validation seeds {validation_seeds[0]}-"
                        f"{validation_seeds[1]}",
                        "validation": validation,
                        "loss": curve,
                        "fit": {k: fitted[k] for k in ("episodes", "mean_abs", "relative")},
                        "checkpoint": str(training.checkpoint(run, step)),
                    }
                )
        if config.expert_row:
            evaluation = EvalConfig(task=task, embodiment=config.embodiment, mode="teleop", **test)
            row = evaluate(evaluation, None, stages, options, f"expert-{task}-test")
            rows.append(_row(row, "human", "VR hand frames", "teleop"))
        for policy in HUB_POLICIES:
            rows.append({"task": task, "policy": policy, "inputs": "", "mode": "",
                         "note": NOT_RUN_OFFLINE})  # fmt: skip
    return {
        "protocol": {**config.protocol.describe(), "embodiment": config.embodiment},
        "config": asdict(config),
        "device": options.device,
        "eval_device": options.eval_device or options.device,
        "rows": rows,
        "stages": stages.records,
        "budget": stages.budget(),
    }


def _row(summary: dict, policy: str, inputs: str, mode: str) -> dict:
    return {
        "task": summary["task"],
        "policy": policy,
        "inputs": inputs,
        "mode": mode,
        "episodes": summary["episodes"],
        "successes": summary["successes"],
        "success_rate": summary["success_rate"],
        "success_ci95": summary["success_ci95"],
        "mean_success_time_s": summary.get("mean_success_time_s"),
        # (absent from evaluations cached before it was recorded)
        "unmet_at_end": summary.get("unmet_at_end", {}),
        "note": "",
    }
