from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")

from beavr_sim.reference import find_reference_dir


@pytest.fixture(scope="session")
def reference_dir() -> Path:
    found = find_reference_dir()
    if found is None:
        pytest.skip(
            "reference models not found: ../shared/reference beside the checkout "
            "(or $BEAVR_REFERENCE_DIR) is absent"
        )
    return found


@pytest.fixture
def pickup_box_with_forced_hold():
    """``make(t0, t1) -> (loop, refusals)``: the bundled PickupBox trace in the in-process
    loop, its guard also refusing the right effector from ``t0`` to ``t1`` (episode seconds);
    ``refusals`` collects the guard's own refusal reasons after ``t1``. Envs closed after."""
    from beavr_sim.assets import bundled_trace
    from beavr_sim.teleop.session import SessionOptions, build_loop
    from beavr_sim.twin.guard import GuardVerdict

    loops = []

    def make(t0: float, t1: float):
        options = SessionOptions(
            task="PickupBox",
            source="trace",
            trace=bundled_trace("PickupBox"),
            viser=False,
            headless=True,
            progress=False,
        )
        loop = build_loop(options)
        loops.append(loop)
        twin, guard = loop.twin, loop.twin.guard
        check = guard.check
        refusals: list[str] = []

        def forced(action, qpos_now, previous=None, reference=None):
            verdict = check(action, qpos_now, previous, reference)
            elapsed = twin.env.elapsed_seconds
            if previous is not None and t0 <= elapsed < t1:
                reasons = {**verdict.reasons, "right": "forced: test hold"}
                return GuardVerdict(tuple(sorted(reasons)), verdict.contacts, reasons)
            if elapsed >= t1:
                refusals.extend(verdict.reasons.values())
            return verdict

        guard.check = forced
        return loop, refusals

    yield make
    for loop in loops:
        loop.twin.env.close()


@pytest.fixture
def quest_push():
    """``connect(context, transport, stream="quest_right") -> socket``: a PUSH socket connected
    to a Quest stream of the detector, as the headset app sends (linger 0). The test closes it
    before terminating its context."""
    import zmq

    def connect(context, transport, stream: str = "quest_right"):
        push = context.socket(zmq.PUSH)
        push.setsockopt(zmq.LINGER, 0)
        push.connect(transport.endpoint(stream, bind=False))
        return push

    return connect


@pytest.fixture
def quest_options():
    """``make(**overrides) -> SessionOptions``: a headless live Quest session (PickupBox, no
    browser view, no progress line) on free ports; ``options.transport`` names them."""
    from beavr_sim.teleop.session import SessionOptions
    from beavr_sim.wire.ports import PortConfig, TransportConfig

    def make(**overrides) -> SessionOptions:
        kwargs = {
            "task": "PickupBox",
            "source": "quest",
            "viser": False,
            "headless": True,
            "progress": False,
            "transport": TransportConfig(ports=PortConfig.free()),
        }
        return SessionOptions(**{**kwargs, **overrides})

    return make


@pytest.fixture(scope="session")
def save_tiny_act_policy():
    """The function below, for tests that need a policy on disk."""
    return _save_tiny_act_policy


def _save_tiny_act_policy(out: Path) -> Path:
    """An untrained, tiny ACT policy on the front camera (24x32) with unit statistics, saved
    to ``out`` with its processors (LeRobot's layout): runs on every task's default robot."""
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy
    from lerobot.policies.factory import make_pre_post_processors

    config = ACTConfig(
        input_features={
            "observation.state": PolicyFeature(FeatureType.STATE, (23,)),
            "observation.images.front": PolicyFeature(FeatureType.VISUAL, (3, 24, 32)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (23,))},
        chunk_size=5,
        n_action_steps=5,
        dim_model=16,
        n_heads=2,
        dim_feedforward=32,
        n_encoder_layers=1,
        n_decoder_layers=1,
        use_vae=False,
        pretrained_backbone_weights=None,
        device="cpu",
        push_to_hub=False,
    )
    torch.manual_seed(0)
    ACTPolicy(config).save_pretrained(out)
    stats = {
        key: {name: torch.zeros(ft.shape) for name in ("mean", "min")}
        | {name: torch.ones(ft.shape) for name in ("std", "max")}
        for key, ft in {**config.input_features, **config.output_features}.items()
    }
    for pipeline in make_pre_post_processors(config, dataset_stats=stats):
        pipeline.save_pretrained(out)
    return out
