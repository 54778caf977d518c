"""Offscreen rendering of the twin's named cameras (shadows and reflections off: several times
faster under Mesa, and what every consumer here wants): the env, the recorder, the policy
evaluation and the headset view all render through :class:`OffscreenCameras`. Depth
(:meth:`OffscreenCameras.render_depth`) is MuJoCo's depth buffer as metres along the camera's
axis, float32; where nothing is drawn it is the far clipping distance."""

from __future__ import annotations

import mujoco
import numpy as np

from beavr_sim.naming import check_name
from beavr_sim.robots.visuals import COLLISION_GROUP, RENDER_GEOM_GROUPS


def render_option(show_collision: bool = False) -> mujoco.MjvOption:
    """The views' geom groups: the scene and the robots' visual geometry; with
    ``show_collision`` the robots' collision geometry too."""
    option = mujoco.MjvOption()
    option.geomgroup[:] = 0
    for group in RENDER_GEOM_GROUPS + ((COLLISION_GROUP,) if show_collision else ()):
        option.geomgroup[group] = 1
    return option


class OffscreenCameras:
    """HxW renders of named cameras of one model (the visual geometry, not the collision
    geometry, unless ``show_collision``)."""

    def __init__(
        self, model: mujoco.MjModel, height: int, width: int, show_collision: bool = False
    ):
        off_h, off_w = model.vis.global_.offheight, model.vis.global_.offwidth
        if height > off_h or width > off_w:
            raise ValueError(
                f"images of {height}x{width} exceed the scene's offscreen buffer "
                f"({off_h}x{off_w}); render at most {off_h}x{off_w}"
            )
        self.height, self.width = int(height), int(width)
        self._model = model
        self._names = tuple(model.camera(i).name for i in range(model.ncam))
        self._renderer: mujoco.Renderer | None = None
        self.option = render_option(show_collision)

    def render(self, data: mujoco.MjData, camera: str) -> np.ndarray:
        """One HxWx3 uint8 frame from ``camera``."""
        check_name("camera", camera, self._names)
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self._model, self.height, self.width)
        self._renderer.update_scene(data, camera=camera, scene_option=self.option)
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        return self._renderer.render().copy()

    def render_depth(self, data: mujoco.MjData, camera: str) -> np.ndarray:
        """One HxWx1 float32 depth image (metres along the camera's axis) from ``camera``."""
        check_name("camera", camera, self._names)
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self._model, self.height, self.width)
        self._renderer.update_scene(data, camera=camera, scene_option=self.option)
        self._renderer.enable_depth_rendering()
        try:
            depth = self._renderer.render()
        finally:
            self._renderer.disable_depth_rendering()
        return depth.astype(np.float32)[..., None]

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
