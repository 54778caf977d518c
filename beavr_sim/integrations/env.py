"""``--env.type=beavr_sim``: the benchmark tasks as a LeRobot env (``lerobot-eval``,
``lerobot-train``'s periodic evaluation).

LeRobot builds the env from :class:`BeavrSimEnvConfig` (``make_env`` ->
:meth:`BeavrSimEnvConfig.create_envs`): ``gym.make("beavr_sim/<Task>-v0", ...)`` in a vector
env, each sub-env behind :class:`LeRobotView`. Observations are the env's own: ``agent_pos``
(measured joints), ``pixels`` (``{camera: HxWx3 uint8}``) and, with ``environment_state=True``,
``environment_state``; ``lerobot.envs.utils.preprocess_observation`` turns them into
``observation.state``, ``observation.images.<camera>`` and ``observation.environment_state``:
the keys ``beavr_sim.datasets`` records, so a policy trained on such a dataset evaluates
without a rename map (set ``cameras``, ``image_height`` / ``image_width`` and
``environment_state`` as the dataset was recorded). ``info["is_success"]`` is set every step.

LeRobot hands an env config no policy, so :meth:`BeavrSimEnvConfig.create_envs` reads the
policy folder of the command line (``--policy.path``, through LeRobot's own parser) and warns
when the env's cameras, image size or ``environment_state`` differ from what the policy was
trained on (``beavr_sim.eval`` takes them from the policy instead).
"""

from __future__ import annotations

import functools
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE

from beavr_sim.envs.registration import ENV_NAMESPACE, env_id
from beavr_sim.envs.scene import check_hand_variant
from beavr_sim.integrations.options import (
    DEFAULT_EMBODIMENT,
    check_cameras,
    check_embodiment,
    check_image_size,
    check_positive_int,
    check_task,
    episode_steps,
)
from beavr_sim.tasks.registry import task_class

#: The env type on LeRobot's command line (``--env.type=beavr_sim``).
ENV_TYPE = "beavr_sim"

log = logging.getLogger(__name__)


def policy_mismatches(
    policy_path: str | Path,
    cameras: list[str],
    image_height: int,
    image_width: int,
    environment_state: bool,
) -> list[str]:
    """How an env with these settings differs from what the pretrained policy at
    ``policy_path`` (its ``config.json``) takes, each with the option that fixes it; empty
    when they agree or the folder holds no readable config."""
    try:
        config = json.loads((Path(policy_path) / "config.json").read_text())
        inputs = dict(config["input_features"])
    except (OSError, ValueError, KeyError, TypeError):
        return []
    images = {
        key.removeprefix(f"{OBS_IMAGES}."): tuple(ft.get("shape", ()))
        for key, ft in inputs.items()
        if key.startswith(f"{OBS_IMAGES}.")
    }
    found: list[str] = []
    if images and set(images) != set(cameras):
        found.append(
            f"cameras {sorted(cameras)}, the policy's {sorted(images)}: "
            f"--env.cameras='[{', '.join(sorted(images))}]'"
        )
    sizes = {shape[1:] for shape in images.values() if len(shape) == 3}
    if len(sizes) == 1:
        ((height, width),) = sizes
        if (height, width) != (image_height, image_width):
            found.append(
                f"images {image_height}x{image_width}, the policy's {height}x{width}: "
                f"--env.image_height={height} --env.image_width={width}"
            )
    wants_state = OBS_ENV_STATE in inputs
    if wants_state != bool(environment_state):
        found.append(
            f"environment_state {str(bool(environment_state)).lower()}, the policy "
            f"{'takes' if wants_state else 'does not take'} it: "
            f"--env.environment_state={str(wants_state).lower()}"
        )
    return found


class LeRobotView(gym.ObservationWrapper):
    """A beavr_sim env as LeRobot's evaluator reads it: ``task_description`` (the task's
    instruction, as ``beavr_sim.datasets`` records it), an integer ``render_fps`` (LeRobot's
    video writer takes no float rate) and, unless kept, no ``environment_state`` in the
    observation (a vision policy trained without it)."""

    def __init__(self, env: gym.Env, environment_state: bool, fps: int):
        super().__init__(env)
        self.metadata = {**env.metadata, "render_fps": int(fps)}
        task = env.unwrapped.task
        self.task_description: str = task.instruction or task.name
        self._keep_state = bool(environment_state)
        spaces = dict(env.observation_space.spaces)
        if not self._keep_state:
            spaces.pop("environment_state", None)
        elif "environment_state" not in spaces:
            raise ValueError(
                f"task {task.name} has no environment_state (no object state): "
                "leave out environment_state=true"
            )
        self.observation_space = gym.spaces.Dict(spaces)

    def observation(self, observation: dict) -> dict:
        if not self._keep_state:
            observation = {k: v for k, v in observation.items() if k != "environment_state"}
        return observation


def make_lerobot_env(
    gym_id: str, gym_kwargs: dict, environment_state: bool, disable_env_checker: bool, fps: int
) -> gym.Env:
    """One sub-env (module level, so ``AsyncVectorEnv`` can pickle it)."""
    env = gym.make(gym_id, disable_env_checker=disable_env_checker, **gym_kwargs)
    return LeRobotView(env, environment_state, fps)


@EnvConfig.register_subclass(ENV_TYPE)
@dataclass
class BeavrSimEnvConfig(EnvConfig):
    """One beavr_sim task for LeRobot (validated in ``__post_init__``; errors list choices)."""

    task: str | None = "PickupBox"
    fps: int = 30
    embodiment: str = DEFAULT_EMBODIMENT
    #: Scene cameras rendered as ``observation.images.<camera>`` (empty: no images).
    cameras: list[str] = field(default_factory=lambda: ["front", "overhead"])
    image_height: int = 480
    image_width: int = 640
    #: Also observe the task's object and target poses (``observation.environment_state``).
    environment_state: bool = False
    #: Control steps per episode (None: the task's own time limit at ``fps``).
    episode_length: int | None = None
    #: The LEAP hands' hardware variant in the twin: "full" or "lite".
    hand_variant: str = "full"

    def __post_init__(self) -> None:
        if self.task is None:
            raise ValueError("--env.task is required for --env.type=beavr_sim")
        embodiment = check_embodiment(self.embodiment)
        self.task = check_task(self.task, self.embodiment)
        self.cameras = list(check_cameras(self.cameras, embodiment))
        check_positive_int("fps", self.fps)
        check_image_size(self.image_height, self.image_width)

        check_hand_variant(embodiment, self.hand_variant)
        self.episode_length = episode_steps(self.task, self.fps, self.episode_length)
        n = len(embodiment.joint_names)
        features: dict[str, PolicyFeature] = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(n,)),
            "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(n,)),
        }
        features_map = {ACTION: ACTION, "agent_pos": OBS_STATE}
        if self.environment_state:
            names = task_class(self.task)(embodiment).state_names
            if not names:
                raise ValueError(
                    f"task {self.task} has no environment_state (no object state): "
                    "leave out --env.environment_state=true"
                )
            features["environment_state"] = PolicyFeature(type=FeatureType.ENV, shape=(len(names),))
            features_map["environment_state"] = OBS_ENV_STATE
        for camera in self.cameras:
            key = f"pixels/{camera}"
            features[key] = PolicyFeature(
                type=FeatureType.VISUAL, shape=(self.image_height, self.image_width, 3)
            )
            features_map[key] = f"{OBS_IMAGES}.{camera}"
        self.features = features
        self.features_map = features_map

    @property
    def package_name(self) -> str:
        return ENV_NAMESPACE

    @property
    def gym_id(self) -> str:
        return env_id(self.task)

    @property
    def gym_kwargs(self) -> dict:
        return {
            "embodiment": self.embodiment,
            "render_mode": "rgb_array",
            "cameras": tuple(self.cameras),
            "control_hz": float(self.fps),
            "camera_height": self.image_height,
            "camera_width": self.image_width,
            "hand_variant": self.hand_variant,
            "max_episode_seconds": self.episode_length / self.fps,
            # gym.make's own: the TimeLimit wrapper lerobot-eval reads (_max_episode_steps).
            "max_episode_steps": self.episode_length,
        }

    def warn_if_policy_differs(self, policy_path: str | Path | None = None) -> list[str]:
        """Log a warning for each way this env differs from the policy at ``policy_path``
        (default: ``--policy.path`` on the command line, if any); returns them."""
        if policy_path is None:
            from lerobot.configs.parser import get_path_arg

            policy_path = get_path_arg("policy")
        if policy_path is None:
            return []
        found = policy_mismatches(
            policy_path, self.cameras, self.image_height, self.image_width, self.environment_state
        )
        for mismatch in found:
            log.warning("the env differs from the policy at %s: %s", policy_path, mismatch)
        return found

    def create_envs(
        self, n_envs: int, use_async_envs: bool = False
    ) -> dict[str, dict[int, gym.vector.VectorEnv]]:
        """``{"beavr_sim": {0: vector env of n_envs}}`` (LeRobot's layout for one task)."""
        check_positive_int("n_envs", n_envs)
        self.warn_if_policy_differs()
        make_one = functools.partial(
            make_lerobot_env,
            self.gym_id,
            self.gym_kwargs,
            self.environment_state,
            self.disable_env_checker,
            self.fps,
        )
        asynchronous = use_async_envs and n_envs > 1
        kwargs: dict = {"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP}
        if asynchronous:
            kwargs["context"] = "forkserver"
        env_cls = gym.vector.AsyncVectorEnv if asynchronous else gym.vector.SyncVectorEnv
        return {self.type: {0: env_cls([make_one] * n_envs, **kwargs)}}
