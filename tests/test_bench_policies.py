"""``python -m beavr_sim.bench policies``: the Wilson interval and the cache key as units, the
training stage's resume and failure paths with a stand-in for ``lerobot-train``, how a policy
with an observation history (Diffusion) is fed in the think-act loop, and one
``--quick`` run end to end (demos -> lerobot-train -> checkpoint choice -> test -> table),
then again from its cache."""

from __future__ import annotations

import json
import math
import sys
from dataclasses import asdict, fields, replace
from pathlib import Path

import pytest

from beavr_sim.bench.policies import train as training
from beavr_sim.bench.policies.config import (
    NOT_RUN_OFFLINE,
    TEST_SEED,
    VALIDATION_SEED,
    AugmentConfig,
    DemoConfig,
    EvalConfig,
    FitConfig,
    Protocol,
    TrainConfig,
    cache_key,
)
from beavr_sim.bench.policies.table import markdown, rate_cell
from beavr_sim.scaling.stats import wilson_interval

DEMOS = DemoConfig(task="PickupBox", episodes=2)
TRAIN = TrainConfig(policy="act", demos=DEMOS, steps=20, save_freq=10, batch_size=8)
EVAL = EvalConfig(task="PickupBox", embodiment="xarm7_leap_right", seed=1000, episodes=2,
                  mode="sync", train_key="abc", step=10, weights="0123")  # fmt: skip


# ---------------------------------------------------------------------------- units
def test_wilson_interval_and_its_table_cell_match_known_values():
    low, high = wilson_interval(8, 10)  # the paper's Diffusion row: 8/10
    assert (round(low, 4), round(high, 4)) == (0.4902, 0.9433)
    low, high = wilson_interval(16, 20)  # the 2026-11-23 ACT figure (docs/benchmarks.md)
    assert (round(low, 4), round(high, 4)) == (0.5840, 0.9193)
    assert rate_cell(16, 20) == "0.80 (0.58-0.92)"
    assert rate_cell(10, 10) == "1.00 (0.72-1.00)"
    assert rate_cell(0, 2) == "0.00 (0.00-0.66)"


def _changed(value):
    """A different value of the same kind."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, int | float):
        return value + 1
    if isinstance(value, tuple):
        return (*value, "front")
    if value is None:
        return 1.0
    return {"PickupBox": "PickPlace", "act": "diffusion", "sync": "async"}.get(value, value + "x")


@pytest.mark.parametrize(
    ("stage", "config"),
    [("demos", DEMOS), ("train", TRAIN), ("eval", EVAL), ("fit", FitConfig("abc", 10, "0123"))],
)
def test_cache_key_changes_with_every_config_field_and_only_then(stage, config):
    key = cache_key(stage, config)
    assert cache_key(stage, replace(config)) == key  # an equal config: the same key
    for f in fields(config):
        value = getattr(config, f.name)
        if isinstance(value, DemoConfig):
            other = replace(value, episodes=value.episodes + 1)
        else:
            other = _changed(value)
        assert cache_key(stage, replace(config, **{f.name: other})) != key, f.name
    assert cache_key("other", config) != key


def test_cache_key_is_stable_across_processes():
    # A literal: no per-process hash seeds, no dict order (bump CACHE_VERSION to change it).
    assert cache_key("demos", DEMOS) == "d3c19f73769f"


def test_protocol_keeps_the_three_seed_ranges_apart():
    with pytest.raises(ValueError, match="into the test seeds"):
        Protocol(demos=200, validation_episodes=20, test_episodes=50)
    with pytest.raises(ValueError, match="must not overlap"):
        Protocol(demos=50, validation_episodes=20, test_episodes=VALIDATION_SEED - TEST_SEED + 1)
    with pytest.raises(ValueError, match="episodes must be >= 1"):
        Protocol(demos=50, validation_episodes=20, test_episodes=0)


def _checkpoint_at(run: Path, step: int) -> None:
    model = training.checkpoint(run, step)
    model.mkdir(parents=True)
    (model / "config.json").write_text("{}")


def _stand_in_lerobot_train(tmp_path: Path, monkeypatch, last_step: int = 20) -> Path:
    """A ``lerobot-train`` that appends its arguments (a JSON line) to the returned file,
    prints a progress bar and saves a checkpoint at ``last_step`` in its ``--output_dir``."""
    calls = tmp_path / "lerobot-train-calls.jsonl"
    script = tmp_path / "lerobot-train"
    script.write_text(
        f"#!{sys.executable}\n"
        "import json, pathlib, sys\n"
        f"with open({str(calls)!r}, 'a') as f:\n"
        "    f.write(json.dumps(sys.argv[1:]) + '\\n')\n"
        "out = next(a for a in sys.argv if a.startswith('--output_dir=')).split('=', 1)[1]\n"
        f"print('Training: 100%|##| {last_step}/{last_step} [00:01<00:00, 9.0step/s]')\n"
        f"model = pathlib.Path(out, 'checkpoints', '{last_step:06d}', 'pretrained_model')\n"
        "model.mkdir(parents=True)\n"
        "(model / 'config.json').write_text('{}')\n"
    )
    script.chmod(0o755)
    monkeypatch.setattr(training, "executable", lambda: str(script))
    return calls


def _calls(calls: Path) -> list[list[str]]:
    return [json.loads(line) for line in calls.read_text().splitlines()] if calls.exists() else []


def test_the_table_says_what_the_failed_episodes_lacked_at_their_end():
    from beavr_sim.eval.runner import EpisodeResult, summarize

    results = [
        EpisodeResult(1000, True, 9.0, 270, final={"lifted": True, "in_area": True}),
        EpisodeResult(1001, False, 20.0, 600, final={"lifted": True, "in_area": False}),
        EpisodeResult(1002, False, 20.0, 600, final={"lifted": False, "in_area": False}),
    ]
    summary = summarize(results, "PickupBox", "xarm7_leap_right", "act", False, 30.0)
    assert summary["unmet_at_end"] == {"in_area": 2, "lifted": 1}  # most first
    assert summary["per_episode"][1] == {
        "seed": 1001, "success": False, "seconds": 20.0, "final": {"lifted": True, "in_area": False}
    }  # fmt: skip
    row = {"task": "PickupBox", "policy": "act", "inputs": "state", "mode": "sync",
           "episodes": 3, "successes": 1, "mean_success_time_s": 9.0,
           "unmet_at_end": summary["unmet_at_end"]}  # fmt: skip
    budget = {"wall_s": 1.0, "cpu_s": 1.0, "stages_cached": 0, "by_stage": {}}
    protocol = {"embodiment": "e", "train_seeds": "0..", "validation_seeds": "2000-2001",
                "test_seeds": "1000-1002"}  # fmt: skip
    text = markdown({"protocol": protocol, "device": "cpu", "budget": budget, "rows": [row]})
    assert "- PickupBox, ACT, sync: of 2 failed, ended without in_area 2, lifted 1" in text
    assert "Open-loop fit" not in text  # a row without one (a table made before it)
    fit = {"episodes": [0, 1], "mean_abs": 0.14161, "relative": 0.5198}
    rows = [row | {"fit": fit, "checkpoint_step": 6000, "train_steps": 6000, "chosen_on": "v"},
            row | {"mode": "async", "fit": fit, "checkpoint_step": 6000, "train_steps": 6000,
                   "chosen_on": "v"}]  # fmt: skip
    text = markdown({"protocol": protocol, "device": "cpu", "budget": budget, "rows": rows})
    assert "on training episodes 0, 1, fed their recorded observations" in text
    line = "- PickupBox, ACT (step 6000): mean |action error| 0.1416, 0.52 of the recorded"
    assert text.count(line) == 1  # once per policy, not per loop
    assert "at each checkpoint" not in text  # validation made before the fit was per checkpoint
    validation = [{"step": 3000, "successes": 0, "episodes": 2, "fit": 0.2, "fit_relative": 0.7},
                  {"step": 6000, "successes": 1, "episodes": 2, "fit": 0.14161,
                   "fit_relative": 0.5198}]  # fmt: skip
    rows = [r | {"validation": validation} for r in rows]
    text = markdown({"protocol": protocol, "device": "cpu", "budget": budget, "rows": rows})
    assert text.count(line) == 1
    assert "spread; at each checkpoint: 3000 0.2000, 6000 0.1416\n" in text


def _bar(n: int, total: int = 3000) -> str:
    return f"Training:  {n * 100 // total}%|##  | {n}/{total} [00:10<01:00,  3.5step/s]"


def test_the_loss_curve_takes_exact_steps_from_the_progress_bar(tmp_path):
    """LeRobot prints ``step:1K`` for 1,000-1,999; the step comes from the progress bar's last
    count before the line, up to the log interval when the bar trails (it redraws at most ten
    times a second); a resumed run's lines replace the cut run's after its checkpoint."""
    log = tmp_path / "train.log"
    line = "INFO 2026-12-04 ot_train.py:641 step:{} smpl:6K ep:2 epch:0.4 loss:{} grdn:3.1"
    log.write_text(
        "$ lerobot-train --log_freq=200\n"
        + _bar(199) + _bar(200) + line.format(200, 2.9) + "\n"
        + _bar(1199) + line.format("1K", 0.5) + "\n"  # the bar one step behind
        + _bar(1400) + line.format("1K", 0.4) + "\n"
        # Resumed from the checkpoint at 1,000: its bar counts the steps since.
        + "$ lerobot-train --config_path=run/checkpoints/001000/pretrained_model/"
        "train_config.json --resume=true --steps=3000\n"
        + _bar(150, 2000) + _bar(200, 2000) + line.format("1K", 0.45) + "\n"
        + _bar(400, 2000) + line.format("1K", 0.44) + "\n"
        # Killed mid-bar (no newline; logs of older versions) and resumed from 1,400.
        + _bar(500, 2000)
        + "$ lerobot-train --config_path=run/checkpoints/001400/pretrained_model/"
        "train_config.json --resume=true --steps=3000\n"
        + _bar(200, 1600) + line.format("1K", 0.43) + "\n"
    )  # fmt: skip
    # What a cut run logged after its checkpoint is replaced by the resumed run's.
    assert training.loss_curve(log, 200) == [
        (200, 2.9), (1200, 0.45), (1400, 0.44), (1600, 0.43)
    ]  # fmt: skip
    # Without a progress bar the lines are counted.
    log.write_text(line.format(200, 1.0) + "\n" + line.format(400, 0.5) + "\n")
    assert training.loss_curve(log, 200) == [(200, 1.0), (400, 0.5)]
    assert training.loss_curve(tmp_path / "missing.log", 200) == []


def test_training_progress_is_read_from_the_log_as_it_grows():
    from beavr_sim.bench.policies.train_progress import RATE_WINDOW_S, TrainProgress, TrainStatus

    now = [0.0]
    progress = TrainProgress(6000, first_step=0, clock=lambda: now[0])
    assert progress.status == TrainStatus(0, 6000)
    now[0] = 10.0
    # a redraw not yet ended by its \r waits; no rate from one step (the start-up before it
    # never counts)
    status = progress.feed(_bar(30, 6000) + "\r" + _bar(40, 6000))
    assert (status.step, status.loss, status.rate) == (30, None, None)
    now[0] = 20.0  # LeRobot's line ends the redraw and brings the loss
    status = progress.feed("\rINFO step:200 smpl:6K loss:1.034 grdn:0.7\n")
    assert (status.step, status.loss, status.rate) == (40, 1.034, 1.0)
    assert status.line("train act on PickupBox") == (
        "train act on PickupBox: step 40/6000 (0 %), 1.00 step/s, ~1 h 39 min left, loss 1.034"
    )
    # the rate is the recent one: a slow start is forgotten after a window
    now[0] = 20.0 + RATE_WINDOW_S + 80.0
    assert progress.feed(_bar(1000, 6000) + "\r").rate == pytest.approx(960 / 380)
    now[0] += RATE_WINDOW_S
    assert progress.feed(_bar(2500, 6000) + "\r").rate == pytest.approx(1500 / RATE_WINDOW_S)
    now[0] += 100.0  # a stall shows: no new step, the rate falls
    assert progress.feed("").rate == pytest.approx(1500 / (RATE_WINDOW_S + 100.0))
    # resumed at the checkpoint at 20,000 of 40,000: its bar counts the steps since
    resumed = TrainProgress(40000, first_step=20000, clock=lambda: now[0])
    assert resumed.status.line("x") == "x: step 20000/40000 (50 %)"
    status = resumed.feed(_bar(1000, 20000) + "\r")
    assert status.step == 21000 and status.rate is None
    now[0] += 10.0
    status = resumed.feed(_bar(6000, 20000) + "\r")
    assert status.step == 26000 and status.rate == 500.0
    assert status.line("x") == "x: step 26000/40000 (65 %), 500.00 step/s, ~28 s left"
    assert TrainStatus(0, 100, rate=0.01).line("x").endswith("~2 h 47 min left")


def test_a_training_run_reports_its_progress_where_stderr_is_a_log(tmp_path, monkeypatch, capsys):
    """Not a terminal (nohup, a CI log): a status line every LINE_EVERY_S, the last one at the
    end of the run."""
    from beavr_sim.bench.policies import train_progress

    monkeypatch.setattr(train_progress, "LINE_EVERY_S", 0.0)
    _stand_in_lerobot_train(tmp_path, monkeypatch)
    training.train(TRAIN, tmp_path / "data", "r/d", tmp_path / "stage")
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines and lines[-1].startswith("train act on PickupBox: step 20/20 (100 %)"), lines


def test_a_cut_training_run_needs_resume_and_continues_from_its_last_checkpoint(
    tmp_path, monkeypatch
):
    stage = tmp_path / "stage"
    _checkpoint_at(stage / "run", 10)  # cut at step 10 of 20
    with pytest.raises(training.TrainUnfinished, match=r"step 10 of 20.*--resume"):
        training.train(TRAIN, tmp_path / "data", "r/d", stage)
    (stage / "train.log").write_text("$ lerobot-train\n" + _bar(12, 20))  # killed mid-bar
    calls = _stand_in_lerobot_train(tmp_path, monkeypatch)
    run = training.train(TRAIN, tmp_path / "data", "r/d", stage, resume=True, loader_workers=3)
    assert run == stage / "run"
    # The resumed run's command starts its own line after the cut bar.
    starts = [ln for ln in (stage / "train.log").read_text().splitlines() if ln.startswith("$ ")]
    assert len(starts) == 2 and "--resume=true" in starts[1], starts
    (command,) = _calls(calls)
    last = training.checkpoint(stage / "run", 10) / "train_config.json"
    assert f"--config_path={last}" in command and "--resume=true" in command
    assert "--steps=20" in command
    assert "--num_workers=3" in command  # the resumed run loads as the fresh one did
    # Finished: nothing runs again.
    assert training.train(TRAIN, tmp_path / "data", "r/d", stage) == stage / "run"
    assert len(_calls(calls)) == 1


def test_extend_continues_the_finished_shorter_run_and_leaves_it_as_it_was(tmp_path, monkeypatch):
    from beavr_sim.bench.policies.stages import RunOptions, Stages, train_policy

    short = replace(TRAIN, steps=10)
    other = replace(TRAIN, steps=5, batch_size=4)  # another configuration: never a source
    for config, key in ((short, "short"), (other, "other")):
        source = tmp_path / "train" / f"act-PickupBox-{key}"
        _checkpoint_at(source / "run", config.steps)
        (source / "train.log").write_text(f"{_bar(10)}step:10 smpl:80 loss:0.5\n")
        (source / "stage.json").write_text(json.dumps({"config": asdict(config)}))
    calls = _stand_in_lerobot_train(tmp_path, monkeypatch)
    assert training.shorter_run(tmp_path / "train", TRAIN) == (
        tmp_path / "train" / "act-PickupBox-short",
        10,
    )
    options = RunOptions(out=tmp_path, extend=True)
    key, run = train_policy(TRAIN, tmp_path / "data", Stages(1, echo=lambda _: None), options)
    (command,) = _calls(calls)
    assert "--resume=true" in command and "--steps=20" in command
    assert f"--config_path={training.checkpoint(run, 10) / 'train_config.json'}" in command
    assert training.saved_steps(run) == [10, 20]  # the source's checkpoint kept
    assert training.saved_steps(tmp_path / "train" / "act-PickupBox-short" / "run") == [10]
    record = json.loads((run.parent / "stage.json").read_text())
    assert record["extended_from"]["steps"] == 10
    assert record["loss"] == [{"step": 10, "loss": 0.5}]  # the source's log came along
    # Nothing shorter of this configuration: a fresh run, from step 0.
    calls.unlink()
    fresh = replace(TRAIN, batch_size=2)
    train_policy(fresh, tmp_path / "data", Stages(1, echo=lambda _: None), options)
    (command,) = _calls(calls)
    assert "--resume=true" not in command


def test_extend_refuses_diffusion_naming_what_it_takes(capsys):
    from beavr_sim.bench.__main__ import main

    assert main(["policies", "--policies", "diffusion", "--extend", "--quick"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: Unknown policy 'diffusion' for --extend.") and "act" in err
    assert len(err.splitlines()) == 1


def test_a_fresh_run_loads_data_with_the_workers_asked_for(tmp_path, monkeypatch):
    monkeypatch.setattr(training, "executable", lambda: "lerobot-train")
    command = training.train_command(TRAIN, tmp_path, "r/d", tmp_path / "run", "cuda", 4)
    assert "--num_workers=4" in command and "--policy.device=cuda" in command
    assert "--num_workers=0" in training.train_command(TRAIN, tmp_path, "r/d", tmp_path, "cpu")


def test_a_failing_lerobot_train_is_one_line_naming_its_log(tmp_path, monkeypatch):
    fail = tmp_path / "lerobot-train"
    fail.write_text(f"#!{sys.executable}\nimport sys\nprint('boom')\nsys.exit(3)\n")
    fail.chmod(0o755)
    monkeypatch.setattr(training, "executable", lambda: str(fail))
    stage = tmp_path / "stage"
    with pytest.raises(training.TrainFailed) as info:
        training.train(TRAIN, tmp_path / "data", "r/d", stage)
    message = str(info.value)
    assert "\n" not in message and "exit 3" in message and str(stage / "train.log") in message
    assert "boom" in (stage / "train.log").read_text()


class _Enough(Exception):
    pass


class _HistoryPolicy:
    """A stand-in policy that looks at its last two observations (as Diffusion does); it ends
    the episode (by raising) once it was handed two."""

    type = "stand-in"
    cameras: dict = {}
    history = 2

    def __init__(self, action):
        self.action = action
        self.seen: list = []

    def reset(self) -> None:
        pass

    def chunk(self, observations, task):
        self.seen.append(observations)
        if isinstance(observations, list) and len(observations) == 2:
            raise _Enough
        return self.action[None]


def test_think_act_hands_a_history_policy_its_consecutive_observations():
    import gymnasium as gym

    from beavr_sim.datasets.recorder import CameraSet
    from beavr_sim.eval.runner import ThinkAct

    env = gym.make("beavr_sim/PickupBox-v0").unwrapped
    cameras = CameraSet.of_env(env, (), 1, 1)
    try:
        env.reset(seed=0)
        policy = _HistoryPolicy(env.agent_pos.copy())
        with pytest.raises(RuntimeError, match="inference failed") as info:
            ThinkAct(env, policy, cameras).run(seed=0, max_seconds=10.0)
    finally:
        cameras.close()
        env.close()
    assert isinstance(info.value.__cause__, _Enough), policy.seen
    first, last = policy.seen[0], policy.seen[-1]
    assert isinstance(first, list) and len(first) == 1  # the first tick: nothing before it
    assert last[0] is not last[1]  # two ticks' observations, not one repeated
    assert set(last[0]) == set(last[1]) >= {"agent_pos"}


def test_a_history_policy_gets_its_observations_stacked_in_time_and_padded():
    torch = pytest.importorskip("torch")
    import numpy as np

    from beavr_sim.eval.policy import LoadedPolicy

    policy = LoadedPolicy.__new__(LoadedPolicy)  # the stacking alone, no folder loaded
    policy._torch, policy.history = torch, 2
    policy._batch = lambda o, task: {
        "observation.state": torch.as_tensor(o["agent_pos"])[None],
        "task": [task],
    }
    one, two, three = ({"agent_pos": np.full(3, v)} for v in (1.0, 2.0, 3.0))
    batch = policy._stacked([one, two, three], "t")
    assert batch["observation.state"].shape == (1, 2, 3) and batch["task"] == ["t"]
    assert batch["observation.state"][0, :, 0].tolist() == [2.0, 3.0]  # the last two, in order
    padded = policy._stacked([one], "t")["observation.state"]  # an episode's first tick
    assert padded[0, :, 0].tolist() == [1.0, 1.0]


# ---------------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """``--quick`` into a fresh folder, then the same command again (all cached) with its
    figure."""
    pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")
    if not Path(sys.executable).with_name("lerobot-train").exists():
        pytest.skip("lerobot-train is not installed beside this Python")
    from beavr_sim.bench.__main__ import main

    out = tmp_path_factory.mktemp("policies")
    assert main(["policies", "--quick", "--out", str(out)]) == 0
    first = json.loads((out / "table.json").read_text())
    assert main(["policies", "--quick", "--out", str(out), "--plot", str(out / "plots")]) == 0
    again = json.loads((out / "table.json").read_text())
    return out, first, again


def test_quick_writes_the_table_and_its_json(quick):
    out, result, _ = quick
    rows = {(r["policy"], r["mode"]): r for r in result["rows"]}
    assert set(rows) == {("act", "sync"), ("act", "async"), ("human", "teleop"),
                         ("smolvla", ""), ("pi0", "")}  # fmt: skip
    for key in (("act", "sync"), ("act", "async"), ("human", "teleop")):
        row = rows[key]
        assert row["episodes"] == 2 and 0 <= row["successes"] <= 2
        assert row["success_ci95"] == [round(v, 4) for v in wilson_interval(row["successes"], 2)]
    assert rows[("human", "teleop")]["successes"] == 2  # the expert succeeds on these seeds
    assert rows[("human", "teleop")]["mean_success_time_s"] > 0
    assert rows[("smolvla", "")]["note"] == rows[("pi0", "")]["note"] == NOT_RUN_OFFLINE
    # The checkpoint was chosen on validation seeds, among the run's checkpoints.
    act = rows[("act", "sync")]
    assert [v["step"] for v in act["validation"]] == [10, 20]
    best = max(act["validation"], key=lambda v: (v["successes"], v["step"]))
    assert act["checkpoint_step"] == best["step"]
    assert Path(act["checkpoint"]).is_dir()
    # The loss as LeRobot logged it (every 10 steps in --quick), at exact steps.
    assert [c["step"] for c in act["loss"]] == [10, 20]
    assert all(math.isfinite(c["loss"]) and c["loss"] > 0 for c in act["loss"])
    # Its open-loop fit on the training episodes: 20 steps leave it far from exact.
    assert act["fit"]["episodes"] == [0, 1] and act["fit"]["mean_abs"] > 0
    assert rows[("act", "async")]["fit"] == act["fit"]
    # ... and every checkpoint's, the chosen one's among them.
    assert all(v["fit"] > 0 and v["fit_relative"] > 0 for v in act["validation"])
    assert {v["step"]: v["fit"] for v in act["validation"]}[best["step"]] == act["fit"]["mean_abs"]
    assert len(list((out / "fit").glob("*.json"))) == 2
    # Training, validation and test seeds are disjoint.
    (demos,) = (out / "demos").glob("*/stage.json")
    train_seeds = set(json.loads(demos.read_text())["seeds"])
    validation = set(range(VALIDATION_SEED, VALIDATION_SEED + 2))
    test = set(range(TEST_SEED, TEST_SEED + 2))
    assert len(train_seeds) == 2 and not train_seeds & validation and not train_seeds & test
    table = (out / "table.md").read_text()
    assert "| PickupBox | ACT | state + object poses | think-act |" in table
    assert f"| PickupBox | SmolVLA |  |  | - | {NOT_RUN_OFFLINE} |" in table
    assert "checkpoints chosen on seeds 2000-2001; tested on seeds 1000-1001" in table
    assert "- PickupBox, ACT (step " in table and "of the recorded actions' spread" in table
    assert result["budget"]["stages_cached"] == 0


def test_quick_again_is_read_from_its_cache(quick):
    _, first, again = quick
    assert all(r["cached"] for r in again["stages"]) and len(again["stages"]) == 9
    assert again["rows"] == first["rows"]
    assert again["budget"]["this_run_wall_s"] == 0
    assert again["budget"]["cpu_s"] == first["budget"]["cpu_s"]


def test_quick_with_plot_draws_each_task_from_the_cached_stages(quick):
    out, _, again = quick
    figure = out / "plots" / "policies_PickupBox.png"
    assert again["plots"] == [str(figure)]
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and figure.stat().st_size > 10_000
    width = int.from_bytes(figure.read_bytes()[16:20], "big")  # the PNG header's IHDR width
    assert width == 1700  # three panels at 100 dpi: the loss, the success, the checkpoints' fit


def test_augment_adds_generated_scenes_to_the_demonstrations_and_is_cached(quick, tmp_path):
    from beavr_sim.bench.policies.config import AUGMENT_SEED
    from beavr_sim.bench.policies.stages import RunOptions, Stages, make_augmented
    from beavr_sim.datasets.shards import read_log

    out, _, _ = quick
    (demos,) = (out / "demos").glob("*/dataset")
    augment = AugmentConfig(source=DEMOS, episodes=1)
    options = RunOptions(out=tmp_path)
    stages = Stages(2, echo=lambda line: None)
    merged = make_augmented(augment, demos, stages, options)
    records = [r for r in read_log(merged) if r.get("kept")]
    seeds = sorted(r["seed"] for r in records)
    # The two demonstrations, then one new scene at or above AUGMENT_SEED (above the test and
    # validation seeds), made from them: no expert.
    demo_seeds = sorted(r["seed"] for r in read_log(demos) if r.get("kept"))
    assert len(seeds) == 3 and seeds[:2] == demo_seeds
    assert seeds[2] >= AUGMENT_SEED > VALIDATION_SEED + 999
    record = stages.records[-1]
    assert record["stage"] == "augment" and not record["cached"]
    assert make_augmented(augment, demos, stages, options) == merged
    assert stages.records[-1]["cached"]


def test_diffusion_learns_its_actions_in_the_range_its_sampler_clips_to():
    """LeRobot's Diffusion clips each denoised sample to [-1, 1] (``clip_sample``): its
    actions must be normalised into that range (MIN_MAX), not to unit variance, where a third
    of the PickupBox demonstrations' values lie outside it and would be cut off."""
    pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    from beavr_sim.bench.policies.config import PRESETS, QUICK_PRESETS

    default = DiffusionConfig()
    assert default.clip_sample and default.clip_sample_range == 1.0
    for presets in (PRESETS, QUICK_PRESETS):
        flags = dict(flag.split("=", 1) for flag in presets["diffusion"].flags)
        assert "clip_sample" not in flags
        mapping = json.loads(flags["normalization_mapping"])
        assert mapping["ACTION"] == "MIN_MAX" and mapping["STATE"] == "MIN_MAX"
        assert mapping["ENV"] == "MIN_MAX"  # the object poses are normalised too
