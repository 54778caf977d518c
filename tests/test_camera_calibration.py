"""Twin cameras at real cameras' poses, and ChArUco calibration recovering a known camera pose
from images the twin renders of a board (issue 40's bound: 5 mm, 0.5 deg)."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from beavr_sim.cameras.calibrate import (
    CharucoBoardSpec,
    calibrate,
    estimate_intrinsics,
    rig_table,
)
from beavr_sim.cameras.errors import CalibrationError
from beavr_sim.envs.camera_pose import CameraIntrinsics, PlacedCamera, place_camera

H, W = 480, 640
PX_PER_SQUARE = 60
MARGIN_SQUARES = 0.5


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def _look_at(pos, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """The optical frame (x right, y down, z forward) of a camera at pos looking at target."""
    z = np.asarray(target, float) - np.asarray(pos, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _board_scene(board: CharucoBoardSpec, T_world_geom: np.ndarray, camera: PlacedCamera):
    """A scratch model: the board as a textured box at T_world_geom, and the camera."""
    grey = board.image(PX_PER_SQUARE)
    pad = int(MARGIN_SQUARES * PX_PER_SQUARE)
    grey = np.pad(grey, pad, constant_values=255)
    rgb = np.repeat(grey[..., None], 3, axis=2)
    spec = mujoco.MjSpec()
    spec.visual.global_.offwidth, spec.visual.global_.offheight = W, H
    spec.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1], diffuse=[0.6] * 3, ambient=[0.5] * 3)
    tex = spec.add_texture(
        name="board", type=mujoco.mjtTexture.mjTEXTURE_2D, width=rgb.shape[1],
        height=rgb.shape[0], nchannel=3,
    )
    tex.data = rgb.tobytes()
    spec.add_material(name="board", textures=["", "board"], texrepeat=[1, 1])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, T_world_geom[:3, :3].flatten())
    body = spec.worldbody.add_body(pos=T_world_geom[:3, 3], quat=quat)
    half = [
        (board.squares_x / 2 + MARGIN_SQUARES) * board.square_m,
        (board.squares_y / 2 + MARGIN_SQUARES) * board.square_m,
        0.002,
    ]
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=half, material="board")
    place_camera(spec, camera)
    model = spec.compile()
    return model, mujoco.MjData(model)


def _T_geom_board(board: CharucoBoardSpec) -> np.ndarray:
    """The box's top face carries the texture's first row at +y, its first column at -x."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = [-board.squares_x * board.square_m / 2, board.squares_y * board.square_m / 2, 0.002]
    return T


def _render(model, data, name="cam") -> np.ndarray:
    mujoco.mj_forward(model, data)
    with mujoco.Renderer(model, H, W) as renderer:
        renderer.update_scene(data, camera=name)
        return renderer.render().copy()


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    cos = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, cos))))


# A board tilted on the table, away from the world origin, and a camera above and to the side.
T_WORLD_GEOM = np.eye(4)
T_WORLD_GEOM[:3, :3] = _rot("z", 25) @ _rot("x", 15)
T_WORLD_GEOM[:3, 3] = [0.45, 0.1, 0.8]
BOARD_KW = dict(squares_x=7, squares_y=5, square_m=0.04, marker_m=0.03, dictionary="DICT_4X4_50")
INTRINSICS = CameraIntrinsics(fx=560.0, fy=555.0, cx=331.0, cy=228.0, width=W, height=H)


@pytest.fixture(scope="module")
def board() -> CharucoBoardSpec:
    T_world_board = T_WORLD_GEOM @ _T_geom_board(CharucoBoardSpec(**BOARD_KW))
    return CharucoBoardSpec(**BOARD_KW, T_world_board=tuple(map(tuple, T_world_board)))


def _camera(pos, target) -> PlacedCamera:
    return PlacedCamera.from_pose("cam", _look_at(pos, target), pos, intrinsics=INTRINSICS)


def test_calibration_recovers_the_rendered_camera_pose(board):
    truth = _camera([0.95, -0.35, 1.45], [0.45, 0.1, 0.8])
    model, data = _board_scene(board, T_WORLD_GEOM, truth)
    image = _render(model, data)
    result = calibrate("front", board, [image], INTRINSICS)
    got = result.camera
    assert result.corners >= 20 and result.reprojection_px < 1.0
    assert np.linalg.norm(got.position - truth.position) < 0.005
    assert _angle_deg(got.R_world_optical, truth.R_world_optical) < 0.5
    table = rig_table(result)
    assert table.startswith("[cameras.front]") and "T_world_camera = [" in table


def test_intrinsics_estimated_from_views(board):
    truth = _camera([0.95, -0.35, 1.45], [0.45, 0.1, 0.8])
    model, data = _board_scene(board, T_WORLD_GEOM, truth)
    cam = model.camera("cam").id
    centre, R_board = T_WORLD_GEOM[:3, 3], T_WORLD_GEOM[:3, :3]
    views = []
    for az in (0, 90, 180, 270):  # around the board, tilted 55 and 30 degrees off its normal
        for el in (35, 60):
            a, e = math.radians(az), math.radians(el)
            pos = centre + 0.55 * R_board @ [math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)]
            R_mj = _look_at(pos, centre, up=R_board[:, 1]) @ np.diag([1.0, -1.0, -1.0])
            mujoco.mju_mat2Quat(model.cam_quat[cam], R_mj.flatten())
            model.cam_pos[cam] = pos
            views.append(_render(model, data))
    intrinsics, _dist, rms = estimate_intrinsics(board, views)
    assert rms < 0.5
    assert abs(intrinsics.fx - INTRINSICS.fx) < 0.01 * INTRINSICS.fx
    assert abs(intrinsics.fy - INTRINSICS.fy) < 0.01 * INTRINSICS.fy
    assert abs(intrinsics.cx - INTRINSICS.cx) < 3 and abs(intrinsics.cy - INTRINSICS.cy) < 3
    with pytest.raises(CalibrationError, match="at least 3 views"):
        estimate_intrinsics(board, views[:2])


def test_board_not_in_view_is_one_line_error(board):
    away = _camera([0.95, -0.35, 1.45], [3.0, -2.0, 1.45])  # looks away from the board
    model, data = _board_scene(board, T_WORLD_GEOM, away)
    with pytest.raises(CalibrationError) as err:
        calibrate("front", board, [_render(model, data)], INTRINSICS)
    message = str(err.value)
    assert "\n" not in message
    assert "board not found" in message and "0 of 17 markers" in message and "'front'" in message


def test_board_spec_errors_list_choices():
    with pytest.raises(CalibrationError, match="DICT_4X4_50"):
        CharucoBoardSpec(**{**BOARD_KW, "dictionary": "DICT_4x4"})
    with pytest.raises(CalibrationError, match="marker_m < square_m"):
        CharucoBoardSpec(**{**BOARD_KW, "marker_m": 0.05})
