"""A LeRobot pretrained policy directory, loaded through LeRobot's factory, behind three calls:
``reset``, ``act`` (one action) and ``chunk`` (an action chunk), on env observations.

A policy that looks at the last ``history`` observations (Diffusion's ``n_obs_steps``) gets
them in ``chunk`` as a list, oldest first; a list shorter than ``history`` (an episode's first
ticks) is padded with its oldest observation, as LeRobot's own ``select_action`` does.

Loading writes nothing on stdout (LeRobot prints ``Loading weights from local directory``
there; it goes to stderr), which the evaluation commands keep for their JSON summary.
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

import numpy as np

IMAGE_PREFIX = "observation.images."
ENV_STATE = "observation.environment_state"


class LoadedPolicy:
    """Policy + its pre/post-processors (normalisation, device) from ``path``."""

    def __init__(self, path: str | Path, device: str = "cpu"):
        path = Path(path)
        if not (path / "config.json").is_file():
            raise FileNotFoundError(
                f"{path} is not a LeRobot pretrained policy folder (no config.json); pass e.g. "
                "outputs/train/<run>/checkpoints/last/pretrained_model"
            )
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors

        self._torch = torch
        config = PreTrainedConfig.from_pretrained(str(path))
        config.device = device
        self.config = config
        self.type = config.type
        with contextlib.redirect_stdout(sys.stderr):
            self.policy = get_policy_class(config.type).from_pretrained(str(path), config=config)
        self.policy.eval()
        self.preprocessor, self.postprocessor = make_pre_post_processors(
            config,
            pretrained_path=str(path),
            preprocessor_overrides={"device_processor": {"device": device}},
        )
        self.cameras: dict[str, tuple[int, int]] = {
            key.removeprefix(IMAGE_PREFIX): (int(ft.shape[1]), int(ft.shape[2]))
            for key, ft in config.input_features.items()
            if key.startswith(IMAGE_PREFIX)
        }
        self.action_dim = int(config.output_features["action"].shape[0])
        #: How many consecutive observations one inference looks at (1 for ACT).
        self.history = max(1, int(getattr(config, "n_obs_steps", 1) or 1))
        self.uses_environment_state = ENV_STATE in config.input_features

    def reset(self) -> None:
        self.policy.reset()
        for pipeline in (self.preprocessor, self.postprocessor):
            reset = getattr(pipeline, "reset", None)
            if callable(reset):
                reset()

    def _batch(self, observation: dict, task: str) -> dict:
        from lerobot.envs.utils import preprocess_observation

        if not self.uses_environment_state:
            observation = {k: v for k, v in observation.items() if k != "environment_state"}
        batch = preprocess_observation(observation)
        batch["task"] = [task]
        return self.preprocessor(batch)

    def act(self, observation: dict, task: str) -> np.ndarray:
        """The policy's next action (its own queue of chunked actions, if it has one)."""
        with self._torch.inference_mode():
            action = self.policy.select_action(self._batch(observation, task))
            action = self.postprocessor(action)
        return action.squeeze(0).cpu().numpy().astype(np.float64)

    def _stacked(self, observations: list[dict], task: str) -> dict:
        """The last ``history`` observations as one batch, stacked along dim 1 (time)."""
        recent = list(observations)[-self.history :]
        recent = [recent[0]] * (self.history - len(recent)) + recent
        batches = [self._batch(o, task) for o in recent]
        torch = self._torch
        return {
            key: torch.stack([b[key] for b in batches], dim=1)
            if isinstance(value, torch.Tensor)
            else value
            for key, value in batches[-1].items()
        }

    def chunk(self, observation: dict | list[dict], task: str) -> np.ndarray:
        """A whole action chunk (k x action_dim) from one observation, or from the recent
        ones (a list, oldest first) for a policy with a ``history``."""
        with self._torch.inference_mode():
            if self.history > 1:
                recent = observation if isinstance(observation, list) else [observation]
                batch = self._stacked(recent, task)
            else:
                batch = self._batch(
                    observation[-1] if isinstance(observation, list) else observation, task
                )
            actions = self.policy.predict_action_chunk(batch)
            actions = self.postprocessor(actions)
        actions = actions.cpu().numpy().astype(np.float64)
        return actions.reshape(-1, actions.shape[-1])
