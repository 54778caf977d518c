"""A viser view of a MuJoCo scene: geometry uploaded once, body poses updated per tick.

Every body that owns visible geoms becomes one scene frame; its geoms are children of that frame,
so an update sends one pose per body, never geometry. Binds 127.0.0.1 unless told otherwise.
"""

from __future__ import annotations

import mujoco
import numpy as np

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080


def _rgb(rgba: np.ndarray) -> tuple[int, int, int]:
    return tuple(int(round(255 * float(c))) for c in rgba[:3])


class TwinView:
    """Live view of ``model``; call :meth:`update` with the current ``MjData``."""

    def __init__(
        self,
        model: mujoco.MjModel,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        title: str = "beavr_sim twin",
        episode_control=None,
    ):
        import viser  # optional dependency (extra "viz")

        self.model = model
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.host, self.port = host, self.server.get_port()
        self.server.scene.add_grid("/floor", width=4.0, height=4.0, cell_size=0.25)
        self.body_frames: dict[int, object] = {}
        self.geom_handles: list[object] = []
        self._add_geoms()
        self.paused = self.server.gui.add_checkbox("Pause", initial_value=False)
        self.reset_requested = False
        reset = self.server.gui.add_button("Reset")
        reset.on_click(lambda _: setattr(self, "reset_requested", True))
        if episode_control is not None:  # recording: start / stop and discard episodes
            record = self.server.gui.add_button("Record: start / stop episode")
            record.on_click(lambda _: episode_control.request("toggle", "browser"))
            discard = self.server.gui.add_button("Discard episode")
            discard.on_click(lambda _: episode_control.request("discard", "browser"))
        self.status = self.server.gui.add_markdown(f"**{title}**")

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def _add_geoms(self) -> None:
        m = self.model
        scene = self.server.scene
        for g in range(m.ngeom):
            if m.geom_group[g] > 2 or m.geom_rgba[g, 3] == 0:
                continue
            gtype, size, color = (
                mujoco.mjtGeom(int(m.geom_type[g])),
                m.geom_size[g],
                _rgb(m.geom_rgba[g]),
            )
            if gtype == mujoco.mjtGeom.mjGEOM_PLANE:
                continue  # the floor is the grid
            body = int(m.geom_bodyid[g])
            if body not in self.body_frames:
                self.body_frames[body] = scene.add_frame(f"/twin/b{body}", show_axes=False)
            name = f"/twin/b{body}/g{g}"
            pose = {"position": m.geom_pos[g], "wxyz": m.geom_quat[g]}
            if gtype == mujoco.mjtGeom.mjGEOM_BOX:
                self.geom_handles.append(scene.add_box(name, color, tuple(2 * size), **pose))
            elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
                self.geom_handles.append(scene.add_icosphere(name, float(size[0]), color, **pose))
            elif gtype in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
                self.geom_handles.append(
                    scene.add_cylinder(name, float(size[0]), float(2 * size[1]), color, **pose)
                )
                if gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
                    R = np.zeros(9)
                    mujoco.mju_quat2Mat(R, m.geom_quat[g])
                    axis = R.reshape(3, 3)[:, 2] * size[1]
                    for k, sign in enumerate((1, -1)):
                        self.geom_handles.append(
                            scene.add_icosphere(
                                f"{name}_cap{k}",
                                float(size[0]),
                                color,
                                position=m.geom_pos[g] + sign * axis,
                            )
                        )

    def update(self, data: mujoco.MjData, status: str | None = None) -> None:
        """Send every moving body's pose (one message batch)."""
        with self.server.atomic():
            for body, frame in self.body_frames.items():
                if (
                    body == 0
                ):  # world-body geoms (table) never move; their frame stays at the origin
                    continue
                frame.position = data.xpos[body]
                frame.wxyz = data.xquat[body]
        if status is not None:
            self.status.content = status

    def close(self) -> None:
        self.server.stop()
