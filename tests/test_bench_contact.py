"""bench contact: settings parsing, the env option, one short run."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import pytest

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.bench import contact
from beavr_sim.envs.scene import DEFAULT_CONTACT, ContactSettings


def test_settings_parse_and_validate():
    assert contact.parse_settings("pyramidal:1, elliptic:10") == (
        ContactSettings("pyramidal", 1.0),
        ContactSettings("elliptic", 10.0),
    )
    with pytest.raises(ValueError, match="elliptic, pyramidal"):
        contact.parse_settings("ellipse:10")
    with pytest.raises(ValueError, match="impratio"):
        ContactSettings("elliptic", 0.5)


def test_the_env_compiles_the_contact_setting():
    env = gym.make("beavr_sim/Playground-v0", contact=ContactSettings("elliptic", 10.0))
    assert env.unwrapped.model.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC
    assert env.unwrapped.model.opt.impratio == 10.0
    env.close()
    env = gym.make("beavr_sim/Playground-v0")
    assert env.unwrapped.model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL == 0
    assert env.unwrapped.model.opt.impratio == DEFAULT_CONTACT.impratio == 1.0
    env.close()


def test_one_episode_reports_success_slip_and_speed():
    result = contact.run((DEFAULT_CONTACT,), ("PickupBox",), episodes=1, progress=False)
    block = result["settings"]["pyramidal:1"]["PickupBox"]
    assert block["success"] == "1/1" and block["failures"] == []
    slip = block["slip_mm_s"]
    assert slip["held_ticks"] > 10  # the box was lifted and held
    assert 0 <= slip["p50"] <= slip["p95"] < 1000
    assert block["ms_per_step"] > 0
