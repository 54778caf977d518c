"""What a policy-table run is: frozen stage configurations, the seed protocol, the policy
presets, and the cache key of a stage.

Seeds (the protocol): demonstrations are recorded from ``TRAIN_SEED`` upwards (a failed
synthesis skips its seed, at most ``5 * demos + 10`` of them), checkpoints are chosen on
``VALIDATION_SEED ..`` and the table is measured on ``TEST_SEED ..``; :class:`Protocol` refuses
counts that would make the three ranges overlap. Episodes generated from the demonstrations
(``--augment``) are new scenes from ``AUGMENT_SEED`` upwards, above all three.

A stage's cache key is a hash of its configuration, the configurations it depends on included
(a training run's key covers its demonstrations'), so changing any field re-runs that stage and
the ones after it, and nothing else. Where a stage runs (``device``, workers) is not part of it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from beavr_sim.naming import check_name

#: First seed of the demonstrations, of the checkpoint-choosing (validation) episodes and of
#: the test episodes; the ranges never overlap (:class:`Protocol`).
TRAIN_SEED = 0
TEST_SEED = 1000
VALIDATION_SEED = 2000
#: First seed of the scenes ``--augment`` generates (above every validation seed: at most
#: ``VALIDATION_SEED - TEST_SEED`` validation episodes).
AUGMENT_SEED = 3000
#: Policies trained here (LeRobot ``--policy.type``).
TRAINED_POLICIES = ("act", "diffusion")
#: Policies whose finished run can be continued to more steps as if it had been asked for them
#: from the start (``--extend``): ACT's learning rate is constant. Diffusion's cosine schedule
#: spans the run's total steps, so a longer run is a different run from its first step.
EXTENDABLE_POLICIES = ("act",)
#: Rows that need pretrained weights from a hub, which an offline machine does not have.
HUB_POLICIES = ("smolvla", "pi0")
NOT_RUN_OFFLINE = "needs pretrained weights from a hub: not run offline"
#: Bumped when a stage's output changes meaning (old caches are then not reused).
CACHE_VERSION = 1


def file_hash(path: Path) -> str:
    """12 hex digits of a hash of the file's bytes."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()[:12]


def cache_key(stage: str, config: object) -> str:
    """12 hex digits of a hash of ``stage`` and the dataclass ``config`` (nested ones too)."""
    payload = json.dumps(
        {"stage": stage, "version": CACHE_VERSION, "config": asdict(config)},
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(payload.encode()).hexdigest()[:12]


@dataclass(frozen=True)
class DemoConfig:
    """Seeded demonstrations of one task (``python -m beavr_sim.datasets generate``)."""

    task: str
    episodes: int
    embodiment: str = "xarm7_leap_right"
    seed: int = TRAIN_SEED
    #: Twin cameras recorded (none: a state policy, which then gets the object poses).
    cameras: tuple[str, ...] = ()
    image_height: int = 96
    image_width: int = 128

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise ValueError(f"demos must be >= 1, got {self.episodes}")

    @property
    def environment_state(self) -> bool:
        """State policies see the object and target poses; image policies see the cameras."""
        return not self.cameras

    @property
    def inputs(self) -> str:
        return "images + state" if self.cameras else "state + object poses"

    @property
    def last_seed(self) -> int:
        """The highest seed the generation may try (every failure skips one)."""
        return self.seed + self.episodes + 5 * self.episodes + 10


@dataclass(frozen=True)
class AugmentConfig:
    """Episodes made from the demonstrations by ``datasets augment`` (MimicGen-style: the
    demonstrations' own motion carried into new scenes, no expert), from ``seed`` upwards;
    training then sees the demonstrations and these together."""

    source: DemoConfig
    episodes: int
    seed: int = AUGMENT_SEED

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise ValueError(f"augment must be >= 1 episodes, got {self.episodes}")


@dataclass(frozen=True)
class TrainConfig:
    """One ``lerobot-train`` run on one demonstration set (and the episodes generated from
    it, ``augmented`` of them)."""

    policy: str
    demos: DemoConfig
    steps: int
    save_freq: int
    batch_size: int = 32
    seed: int = 0
    #: Extra ``--policy.*`` flags (the preset), as ``name=value`` pairs.
    policy_flags: tuple[str, ...] = ()
    #: Episodes generated from the demonstrations and trained on with them (0: none).
    augmented: int = 0

    def __post_init__(self) -> None:
        check_name("policy", self.policy, TRAINED_POLICIES)
        if self.augmented < 0:
            raise ValueError(f"augmented must be >= 0, got {self.augmented}")
        if self.steps < 1 or self.save_freq < 1 or self.batch_size < 1:
            raise ValueError(
                f"steps, save_freq and batch_size must be >= 1, got {self.steps}, "
                f"{self.save_freq}, {self.batch_size}"
            )


@dataclass(frozen=True)
class EvalConfig:
    """Episodes of one policy checkpoint (or of the scripted expert through the teleop
    pipeline: ``checkpoint == ""``) on seeds ``seed .. seed + episodes - 1``."""

    task: str
    embodiment: str
    seed: int
    episodes: int
    mode: str  # "sync", "async" (think-act) or "teleop" (the expert's row)
    #: The training run, the checkpoint's step and a hash of its weights (a run trained anew
    #: into the same folder is not mistaken for the one evaluated); "" / 0 for the expert.
    train_key: str = ""
    step: int = 0
    weights: str = ""
    max_seconds: float | None = None

    def __post_init__(self) -> None:
        check_name("evaluation mode", self.mode, ("sync", "async", "teleop"))
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")


#: The training episodes a checkpoint's open-loop fit is measured on.
FIT_EPISODES = (0, 1)


@dataclass(frozen=True)
class FitConfig:
    """The open-loop fit of one checkpoint (``python -m beavr_sim.eval.fit``): its actions on
    recorded training episodes against the recorded ones, the check that tells a policy that
    never learned its data from one that drifts in the env."""

    train_key: str
    step: int
    weights: str
    episodes: tuple[int, ...] = FIT_EPISODES


@dataclass(frozen=True)
class Protocol:
    """The seeds of one table: demonstrations, validation, test (disjoint, checked)."""

    demos: int
    validation_episodes: int
    test_episodes: int

    def __post_init__(self) -> None:
        for name, n in (
            ("demos", self.demos),
            ("validation episodes", self.validation_episodes),
            ("episodes", self.test_episodes),
        ):
            if n < 1:
                raise ValueError(f"{name} must be >= 1, got {n}")
        demo_last = TRAIN_SEED + 6 * self.demos + 10
        if demo_last >= TEST_SEED:
            raise ValueError(
                f"{self.demos} demos may try seeds up to {demo_last}, into the test seeds "
                f"({TEST_SEED}..); at most {(TEST_SEED - TRAIN_SEED - 11) // 6} demos"
            )
        for name, n in (("test", self.test_episodes), ("validation", self.validation_episodes)):
            if n > VALIDATION_SEED - TEST_SEED:
                raise ValueError(
                    f"at most {VALIDATION_SEED - TEST_SEED} {name} episodes (the seed ranges "
                    f"{TEST_SEED}.. and {VALIDATION_SEED}.. must not overlap), got {n}"
                )

    def describe(self) -> dict:
        return {
            "train_seeds": f"{TRAIN_SEED}.. ({self.demos} successful demos; failed syntheses skip "
            "their seed)",
            "validation_seeds": f"{VALIDATION_SEED}-{VALIDATION_SEED + self.validation_episodes - 1}",
            "test_seeds": f"{TEST_SEED}-{TEST_SEED + self.test_episodes - 1}",
        }


@dataclass(frozen=True)
class PolicyPreset:
    """A policy's training settings: steps, checkpoint interval, batch, ``--policy.*`` flags."""

    steps: int
    save_freq: int
    batch_size: int
    flags: tuple[str, ...] = field(default_factory=tuple)


#: Normalise the object poses too (ACT's default mapping leaves ``ENV`` features raw).
_NORMALISE_ALL = (
    'normalization_mapping={"VISUAL":"MEAN_STD","STATE":"MEAN_STD","ENV":"MEAN_STD",'
    '"ACTION":"MEAN_STD"}'
)
#: Diffusion's: actions and states to [-1, 1] (LeRobot's default for it, object poses added).
#: Its sampler clips every denoised sample to [-1, 1] (``clip_sample``); with MEAN_STD a third
#: of the PickupBox demonstrations' action values lie beyond one standard deviation, and the
#: clip cut them off.
_MIN_MAX_ALL = (
    'normalization_mapping={"VISUAL":"MEAN_STD","STATE":"MIN_MAX","ENV":"MIN_MAX",'
    '"ACTION":"MIN_MAX"}'
)
_NO_HUB = ("pretrained_backbone_weights=null",)  # offline: ResNet from scratch

#: The table's settings: ACT as in docs/benchmarks.md (4.3 M parameters, chunk 30, 10 actions
#: per chunk), Diffusion with a smaller U-Net and 10 DDIM steps at inference (CPU-sized).
PRESETS: dict[str, PolicyPreset] = {
    "act": PolicyPreset(
        steps=6000,
        save_freq=1000,
        batch_size=32,
        flags=(
            *_NO_HUB,
            "chunk_size=30",
            "n_action_steps=10",
            "dim_model=256",
            "dim_feedforward=1024",
            "n_encoder_layers=2",
            "n_vae_encoder_layers=2",
            "optimizer_lr=1e-4",
            _NORMALISE_ALL,
        ),
    ),
    "diffusion": PolicyPreset(
        steps=6000,
        save_freq=1000,
        batch_size=32,
        flags=(
            "n_obs_steps=2",
            "horizon=16",
            "n_action_steps=8",
            "drop_n_last_frames=7",  # horizon - n_action_steps - n_obs_steps + 1
            "down_dims=[128,256,512]",
            "noise_scheduler_type=DDIM",
            "num_inference_steps=10",
            _MIN_MAX_ALL,
        ),
    ),
}

#: ``--quick``: tiny models and 20 steps, checkpoints at 10 and 20 (what the tests run).
QUICK_PRESETS: dict[str, PolicyPreset] = {
    "act": PolicyPreset(
        steps=20,
        save_freq=10,
        batch_size=8,
        flags=(
            *_NO_HUB,
            "chunk_size=10",
            "n_action_steps=10",
            "dim_model=32",
            "dim_feedforward=64",
            "n_heads=2",
            "n_encoder_layers=1",
            "n_vae_encoder_layers=1",
            _NORMALISE_ALL,
        ),
    ),
    "diffusion": PolicyPreset(
        steps=20,
        save_freq=10,
        batch_size=8,
        flags=(
            "n_obs_steps=2",
            "horizon=8",
            "n_action_steps=4",
            "drop_n_last_frames=3",
            "down_dims=[16,32]",
            "diffusion_step_embed_dim=16",
            "noise_scheduler_type=DDIM",
            "num_train_timesteps=10",
            "num_inference_steps=2",
            _MIN_MAX_ALL,
        ),
    ),
}
