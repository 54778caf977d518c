"""``python -m beavr_sim.datasets generate``: demonstrations from synthesized VR traces.

Per episode: the task's scripted expert drives a synthetic operator's hands (the inverse of the
operator mapping and a human hand model, with tracking noise and dropouts; see
:mod:`beavr_sim.synthetic.trace`), the frames are saved as a VR trace, and the trace is replayed
through the full teleop pipeline (validator, operator, twin) while the recorder writes LeRobot
frames. The data is therefore what a VR operator's session produces, not expert actions. The
traces are kept in ``<out>/beavr_traces/`` so every episode can be replayed or re-recorded.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from beavr_sim.datasets.features import RecordingConfig, lerobot_features
from beavr_sim.datasets.recorder import EpisodeRecorder, run_recorded_episode
from beavr_sim.datasets.writer import EpisodeWriter


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
) -> GenerateSummary:
    import gymnasium as gym

    from beavr_sim.synthetic.trace import quantize, synthesize, write_trace
    from beavr_sim.tasks.registry import canonical_task_name
    from beavr_sim.teleop.session import SessionOptions, build_loop

    task = canonical_task_name(task)
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    config = config or RecordingConfig()
    out = Path(out)
    repo_id = repo_id or f"beavr_sim/{task.lower()}"
    probe = gym.make(f"beavr_sim/{task}-v0", embodiment=embodiment).unwrapped
    if int(round(probe.control_hz)) != config.fps:
        raise ValueError(f"fps must equal the env's control rate ({probe.control_hz:g} Hz)")
    features = lerobot_features(probe.embodiment, config, probe.environment_state_names)
    probe.close()
    writer = EpisodeWriter(
        out,
        repo_id,
        features,
        config.fps,
        robot_type=embodiment,
        use_videos=config.use_videos,
        overwrite=overwrite,
    )
    summary = GenerateSummary(task, embodiment, str(out), repo_id, episodes, 0, 0, 0)
    start = time.perf_counter()
    trace_dir = out / "beavr_traces"
    bar = tqdm(total=episodes, desc=f"{task} demos", unit="ep", disable=not progress)
    episode_seed = seed
    try:
        while summary.episodes_written < episodes:
            result = synthesize(task, episode_seed, embodiment, quantize=quantize)
            ok = bool(result.summary.success)
            summary.successes += int(ok)
            summary.failures += int(not ok)
            if not ok:
                summary.seeds_failed.append(episode_seed)
            if ok or keep_failed:
                trace = write_trace(
                    trace_dir / f"{task.lower()}_seed{episode_seed:05d}.mcap", result
                )
                options = SessionOptions(
                    task=task,
                    source="trace",
                    trace=trace,
                    viser=False,
                    headless=True,
                    progress=False,
                )
                loop = build_loop(options)
                recorder = EpisodeRecorder(writer, loop.twin.env, config)
                try:
                    replayed = run_recorded_episode(loop, recorder, config)
                    written = recorder.end(
                        keep=replayed.success or keep_failed,
                        success=bool(replayed.success),
                        seed=episode_seed,
                        source=f"synth trace {trace.name}",
                    )
                finally:
                    recorder.close()
                    loop.twin.env.close()
                if written:
                    summary.episodes_written += 1
                    summary.frames += recorder.frames
                    bar.update(1)
            bar.set_postfix(ok=summary.successes, failed=summary.failures)
            episode_seed += 1
            if summary.failures > 5 * episodes + 10:
                print(f"giving up: {summary.failures} failed episodes", file=sys.stderr)
                break
    finally:
        bar.close()
        writer.close()
    summary.wall_s = round(time.perf_counter() - start, 2)
    return summary
