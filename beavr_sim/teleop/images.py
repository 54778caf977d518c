"""The headset camera's images of the twin: which camera, the pose a render needs (copied on
the control thread) and the renderer (on a viewer's thread). Used by the single-process session
and the ``--multiprocess`` twin process.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def headset_camera(embodiment) -> str:
    """The camera whose images go to the headset: the robot's own first camera where it has one
    (the RX-1's ``head``: the operator sees what the robot's head sees), else ``front``."""
    return embodiment.cameras[0] if embodiment.cameras else "front"


@dataclass(frozen=True)
class ScenePose:
    """What a render of the scene needs of the env's state, copied on the control thread."""

    qpos: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray

    @classmethod
    def of(cls, data) -> ScenePose:
        return cls(data.qpos.copy(), data.mocap_pos.copy(), data.mocap_quat.copy())


class HeadsetRenderer:
    """Renders the headset camera from a :class:`ScenePose` into its own ``MjData`` and
    publishes the image; it runs on a :class:`ThreadedListener`'s thread, so it never reads the
    env's ``MjData`` while the control thread steps it."""

    def __init__(self, publisher, model, camera: str, size: tuple[int, int]):
        import mujoco

        from beavr_sim.envs.cameras import OffscreenCameras  # local: heavy (mujoco)

        self.publisher = publisher
        self.model = model
        self.camera = camera
        self.data = mujoco.MjData(model)
        self.cameras = OffscreenCameras(model, size[1], size[0])

    def __call__(self, pose: ScenePose) -> None:
        import mujoco

        self.data.qpos[:] = pose.qpos
        self.data.mocap_pos[:] = pose.mocap_pos
        self.data.mocap_quat[:] = pose.mocap_quat
        mujoco.mj_forward(self.model, self.data)
        self.publisher.publish(self.cameras.render(self.data, self.camera))

    def close(self) -> None:
        self.cameras.close()
