"""Twin cameras at real cameras' poses, and ChArUco calibration recovering a known camera pose
from images the twin renders of a board (issue 40's bound: 5 mm, 0.5 deg)."""

from __future__ import annotations

import math
import tomllib

import cv2
import mujoco
import numpy as np
import pytest

from beavr_sim.cameras.__main__ import main as cameras_main
from beavr_sim.cameras.calibrate import (
    CharucoBoardSpec,
    calibrate,
    detect,
    estimate_intrinsics,
    load_board,
)
from beavr_sim.cameras.errors import CalibrationError
from beavr_sim.cameras.poses import placed_camera
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
        name="board",
        type=mujoco.mjtTexture.mjTEXTURE_2D,
        width=rgb.shape[1],
        height=rgb.shape[0],
        nchannel=3,
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


def _render(model, data, renderer: mujoco.Renderer | None = None) -> np.ndarray:
    mujoco.mj_forward(model, data)
    if renderer is None:
        with mujoco.Renderer(model, H, W) as own:
            return _render(model, data, own)
    renderer.update_scene(data, camera="cam")
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


def _assert_pose_close(got: PlacedCamera, truth: PlacedCamera) -> None:
    assert np.linalg.norm(got.position - truth.position) < 0.005  # 5 mm
    assert _angle_deg(got.R_world_optical, truth.R_world_optical) < 0.5  # 0.5 deg


def _board_toml(board: CharucoBoardSpec) -> str:
    rows = ", ".join("[" + ", ".join(repr(v) for v in row) + "]" for row in board.T_world_board)
    return (
        f"[board]\nsquares_x = {board.squares_x}\nsquares_y = {board.squares_y}\n"
        f"square_m = {board.square_m}\nmarker_m = {board.marker_m}\n"
        f'dictionary = "{board.dictionary}"\nT_world_board = [{rows}]\n'
    )


def test_calibration_recovers_the_rendered_camera_pose(board, tmp_path, capsys):
    truth = _camera([0.95, -0.35, 1.45], [0.45, 0.1, 0.8])
    model, data = _board_scene(board, T_WORLD_GEOM, truth)
    image = _render(model, data)
    result = calibrate("front", board, [image], INTRINSICS)
    assert result.corners >= 20 and result.reprojection_px < 1.0
    _assert_pose_close(result.camera, truth)

    # The command line: board file + image file -> the rig table, which places the twin camera.
    (tmp_path / "board.toml").write_text(_board_toml(board))
    cv2.imwrite(str(tmp_path / "front.png"), image[..., ::-1])
    k = INTRINSICS
    code = cameras_main(
        [
            "calibrate",
            "--board",
            str(tmp_path / "board.toml"),
            "--camera",
            "front",
            "--images",
            str(tmp_path / "front.png"),
            "--intrinsics",
            f"{k.fx},{k.fy},{k.cx},{k.cy}",
        ]
    )
    assert code == 0
    table = capsys.readouterr().out
    assert table.startswith("[cameras.front]") and "T_world_camera = [" in table
    rig = tomllib.loads(
        table.replace("[cameras.front]", '[cameras.front]\ntype = "opencv"\nindex_or_path = 0')
    )
    placed = placed_camera("front", rig["cameras"]["front"])
    _assert_pose_close(placed, truth)
    assert placed.intrinsics == INTRINSICS


def test_intrinsics_estimated_from_views(board):
    truth = _camera([0.95, -0.35, 1.45], [0.45, 0.1, 0.8])
    model, data = _board_scene(board, T_WORLD_GEOM, truth)
    cam = model.camera("cam").id
    centre, R_board = T_WORLD_GEOM[:3, 3], T_WORLD_GEOM[:3, :3]
    views = []
    renderer = mujoco.Renderer(model, H, W)
    for az in (0, 90, 180, 270):  # around the board, tilted 55 and 30 degrees off its normal
        for el in (35, 60):
            a, e = math.radians(az), math.radians(el)
            pos = centre + 0.55 * R_board @ [
                math.cos(a) * math.cos(e),
                math.sin(a) * math.cos(e),
                math.sin(e),
            ]
            R_mj = _look_at(pos, centre, up=R_board[:, 1]) @ np.diag([1.0, -1.0, -1.0])
            mujoco.mju_mat2Quat(model.cam_quat[cam], R_mj.flatten())
            model.cam_pos[cam] = pos
            views.append(_render(model, data, renderer))
    renderer.close()
    intrinsics, _dist, rms = estimate_intrinsics(board, views)
    assert rms < 0.5
    assert abs(intrinsics.fx - INTRINSICS.fx) < 0.01 * INTRINSICS.fx
    assert abs(intrinsics.fy - INTRINSICS.fy) < 0.01 * INTRINSICS.fy
    assert abs(intrinsics.cx - INTRINSICS.cx) < 3 and abs(intrinsics.cy - INTRINSICS.cy) < 3
    with pytest.raises(CalibrationError, match="at least 3 views"):
        estimate_intrinsics(board, views[:2])


def test_board_not_in_view_is_one_line_error(board, tmp_path, capsys):
    away = _camera([0.95, -0.35, 1.45], [3.0, -2.0, 1.45])  # looks away from the board
    model, data = _board_scene(board, T_WORLD_GEOM, away)
    image = _render(model, data)
    with pytest.raises(CalibrationError) as err:
        calibrate("front", board, [image], INTRINSICS)
    message = str(err.value)
    assert "\n" not in message
    assert "board not found" in message and "0 of 17 markers" in message and "'front'" in message
    (tmp_path / "board.toml").write_text(_board_toml(board))
    cv2.imwrite(str(tmp_path / "away.png"), image)
    code = cameras_main(
        [
            "calibrate",
            "--board",
            str(tmp_path / "board.toml"),
            "--camera",
            "front",
            "--images",
            str(tmp_path / "away.png"),
            "--intrinsics-images",
            str(tmp_path / "away.png"),
        ]
    )
    err_lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err_lines) == 1 and "at least 3 views" in err_lines[0]
    code = cameras_main(
        [
            "calibrate",
            "--board",
            str(tmp_path / "board.toml"),
            "--camera",
            "front",
            "--images",
            str(tmp_path / "away.png"),
            "--intrinsics",
            "560,555,331,228",
        ]
    )
    err_lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err_lines) == 1 and "board not found (0 of 17 markers" in err_lines[0]


def test_board_spec_errors_list_choices():
    with pytest.raises(CalibrationError, match="DICT_4X4_50"):
        CharucoBoardSpec(**{**BOARD_KW, "dictionary": "DICT_4x4"})
    with pytest.raises(CalibrationError, match="marker_m < square_m"):
        CharucoBoardSpec(**{**BOARD_KW, "marker_m": 0.05})


def test_board_command_prints_a_detectable_board(board, tmp_path):
    (tmp_path / "board.toml").write_text(_board_toml(board))
    out = tmp_path / "board.png"
    assert (
        cameras_main(
            [
                "board",
                "--board",
                str(tmp_path / "board.toml"),
                "--out",
                str(out),
                "--px-per-square",
                "40",
            ]
        )
        == 0
    )
    found = detect(board, cv2.imread(str(out), cv2.IMREAD_GRAYSCALE))
    assert len(found.object_points) == (board.squares_x - 1) * (board.squares_y - 1)
    (tmp_path / "bad.toml").write_text(_board_toml(board).replace("square_m", "square_mm"))
    with pytest.raises(CalibrationError, match=r"unknown \[board\] keys \['square_mm'\]; valid"):
        load_board(tmp_path / "bad.toml")
