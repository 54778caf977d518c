"""Errors a new user meets in the first hour name the cause: the emulators' ``--help``, a
truncated trace (and ``traces recover``), a text file for ``--qpos-file``, ``lerobot-eval``
with an env that differs from the policy, ``--episodes`` without ``--record``; recording one
trace several times says the episodes are the same."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import numpy as np
import pytest

from beavr_sim.assets import bundled_trace
from beavr_sim.teleop.session import SessionOptions, repeated_trace_note
from beavr_sim.traces.format import TraceReader, TraceTruncatedError

ROOT = Path(__file__).resolve().parents[1]


def test_emulators_help_and_a_bad_plan(capsys):
    from beavr_sim.hardware.emulators import main

    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "usage: python -m beavr_sim.hardware.emulators" in out and "PLAN" in out
    with pytest.raises(SystemExit) as exit_info:
        main(["[1"])
    assert exit_info.value.code == 2
    assert "PLAN is not JSON" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(['[["arm", "xarm7"]]'])
    assert "[name, kind, start]" in capsys.readouterr().err


def test_a_truncated_trace_says_where_and_traces_recover_keeps_its_frames(tmp_path, capsys):
    from beavr_sim.traces.__main__ import main

    source = bundled_trace("Pour")
    whole = TraceReader(source)
    full = [e for e in whole.events() if e[1] == "hand"]
    data = source.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(TraceTruncatedError) as info:
        TraceReader(cut)
    message = str(info.value)
    assert f"truncated at byte {len(data) // 2}" in message
    kept = info.value.salvage.hand_frames
    assert 0 < kept < len(full) and f"the first {kept} hand frames" in message
    assert f"python -m beavr_sim.traces recover {cut}" in message
    assert "RecordLengthLimitExceeded" not in message

    out = tmp_path / "fixed.mcap"
    assert main(["recover", str(cut), "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["hand_frames"] == kept and summary["metadata_recovered"]
    fixed = TraceReader(out)
    frames = [e for e in fixed.events() if e[1] == "hand"]
    assert len(frames) == kept and fixed.metadata.task == whole.metadata.task
    for (t, _, a), (u, _, b) in zip(frames, full[:kept], strict=False):
        assert t == u and a.side == b.side
        np.testing.assert_array_equal(a.joints, b.joints)

    # Cut inside the first compressed block: nothing to read, and it says so.
    early = tmp_path / "early.mcap"
    early.write_bytes(data[:1000])
    with pytest.raises(TraceTruncatedError, match="no hand frame before the cut is readable"):
        TraceReader(early)


def test_a_text_qpos_file_is_named_as_not_npy(tmp_path, capsys):
    from beavr_sim.hardware.guard import main

    text = tmp_path / "q.txt"
    text.write_text(" ".join(["0.0"] * 23) + "\n")
    assert main(["--qpos-file", str(text)]) == 2
    err = capsys.readouterr().err
    assert "is not a .npy file" in err and "numpy.save" in err and "pickled" not in err


def test_lerobot_eval_warns_when_the_env_renders_other_images_than_the_policy_takes(
    tmp_path, monkeypatch, caplog
):
    pytest.importorskip("lerobot", reason="lerobot (>= 0.5) is not installed")
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig

    from beavr_sim.integrations.env import BeavrSimEnvConfig

    policy = tmp_path / "policy"
    policy.mkdir()
    ACTConfig(
        input_features={
            "observation.state": PolicyFeature(FeatureType.STATE, (23,)),
            "observation.images.front": PolicyFeature(FeatureType.VISUAL, (3, 24, 32)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (23,))},
        pretrained_backbone_weights=None,
        device="cpu",
        push_to_hub=False,
    )._save_pretrained(policy)
    env = BeavrSimEnvConfig(task="PickupBox", cameras=["front"], image_height=48, image_width=64)
    monkeypatch.setattr(sys, "argv", ["lerobot-eval", f"--policy.path={policy}"])
    with caplog.at_level(logging.WARNING, logger="beavr_sim.integrations.env"):
        envs = env.create_envs(1)
    for vector in envs[env.type].values():
        vector.close()
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any(
        "images 48x64, the policy's 24x32: --env.image_height=24 --env.image_width=32" in w
        for w in warnings
    ), warnings
    same = BeavrSimEnvConfig(task="PickupBox", cameras=["front"], image_height=24, image_width=32)
    assert same.warn_if_policy_differs(policy) == []
    both = BeavrSimEnvConfig(task="PickupBox", image_height=24, image_width=32)
    assert any("--env.cameras='[front]'" in m for m in both.warn_if_policy_differs(policy))


@pytest.mark.parametrize(("episodes", "said"), [(2, True), (1, False)])
def test_recording_a_trace_twice_says_the_episodes_are_the_same(tmp_path, episodes, said):
    options = SessionOptions(task="pour", source="trace", record=tmp_path, episodes=episodes)
    note = repeated_trace_note(options, seed=0)
    assert bool(note) is said
    if said:
        assert "same demonstration 2 times (seed 0" in note and "datasets generate" in note


def test_episodes_without_record_is_refused_not_ignored():
    with pytest.raises(ValueError, match="--episodes needs --record"):
        SessionOptions(task="pour", source="trace", episodes=3)
