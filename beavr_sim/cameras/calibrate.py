"""Camera calibration from a ChArUco board at a known pose in the world frame (OpenCV's aruco).

A :class:`CharucoBoardSpec` is the printed board (squares, square and marker size in metres,
ArUco dictionary) and its pose ``T_world_board``: the board frame is OpenCV's ChArUco frame,
origin at the outer corner of the board's top-left square (as :meth:`CharucoBoardSpec.image`
draws it), x along a row to the right, y down the columns, z into the board.
:func:`calibrate` detects the board's corners in images taken by a fixed camera with the board
at that pose, takes the camera's intrinsics as given or estimates them from other views of
the board (:func:`estimate_intrinsics`, at least 3), solves the camera's pose
(``cv2.solvePnP`` on every image's corners together) and returns a
:class:`~beavr_sim.envs.camera_pose.PlacedCamera`; :func:`rig_table` writes it as the rig
file's ``[cameras.NAME]`` keys. An image where the board is not found raises one
:class:`CalibrationError` line saying how many markers and corners were seen.
Lens distortion is estimated with the intrinsics and used for the pose, but the twin renders
an undistorted pinhole.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from beavr_sim.cameras.errors import CalibrationError
from beavr_sim.envs.camera_pose import CameraIntrinsics, PlacedCamera

#: ArUco dictionaries by OpenCV's name (DICT_4X4_50, DICT_5X5_100, ...).
DICTIONARIES: dict[str, int] = {
    name: getattr(cv2.aruco, name) for name in dir(cv2.aruco) if name.startswith("DICT_")
}
#: Fewest ChArUco corners an image must show to count (OpenCV's PnP needs 4 non-collinear).
MIN_CORNERS = 6
MIN_INTRINSICS_VIEWS = 3


def _pose_matrix(value, what: str) -> np.ndarray:
    T = np.asarray(value, dtype=float)
    if T.shape != (4, 4) or not np.isfinite(T).all() or not np.allclose(T[3], (0, 0, 0, 1)):
        raise CalibrationError(f"{what} must be a 4x4 matrix with last row [0, 0, 0, 1]")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise CalibrationError(f"{what}: the top-left 3x3 is not a rotation")
    return T


@dataclass(frozen=True)
class CharucoBoardSpec:
    """A ChArUco board and its pose in the world frame (see the module docstring)."""

    squares_x: int
    squares_y: int
    square_m: float
    marker_m: float
    dictionary: str = "DICT_4X4_50"
    T_world_board: tuple[tuple[float, ...], ...] = tuple(map(tuple, np.eye(4)))

    def __post_init__(self) -> None:
        if self.dictionary not in DICTIONARIES:
            raise CalibrationError(
                f"board dictionary {self.dictionary!r} is not one of {sorted(DICTIONARIES)}"
            )
        if not (self.squares_x >= 2 and self.squares_y >= 2):
            raise CalibrationError(
                f"board needs squares_x, squares_y >= 2, got {self.squares_x}x{self.squares_y}"
            )
        if not 0 < self.marker_m < self.square_m:
            raise CalibrationError(
                f"board needs 0 < marker_m < square_m, got {self.marker_m} and {self.square_m}"
            )
        T = _pose_matrix(self.T_world_board, "board T_world_board")
        object.__setattr__(self, "T_world_board", tuple(tuple(float(v) for v in r) for r in T))

    @property
    def board(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(DICTIONARIES[self.dictionary])
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_m, self.marker_m, dictionary
        )

    def image(self, px_per_square: int) -> np.ndarray:
        """The board as a grey uint8 image, ``px_per_square`` pixels a square, no margin."""
        size = (self.squares_x * px_per_square, self.squares_y * px_per_square)
        return self.board.generateImage(size, marginSize=0, borderBits=1)


def load_board(path: str | Path) -> CharucoBoardSpec:
    """A board file's ``[board]`` table (the :class:`CharucoBoardSpec` fields)."""
    try:
        with open(path, "rb") as f:
            table = tomllib.load(f).get("board")
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise CalibrationError(f"{path}: {exc}") from None
    valid = [f.name for f in dataclasses.fields(CharucoBoardSpec)]
    if not isinstance(table, dict):
        raise CalibrationError(f"{path}: needs a [board] table with keys {valid}")
    unknown = sorted(set(table) - set(valid))
    if unknown:
        raise CalibrationError(f"{path}: unknown [board] keys {unknown}; valid: {valid}")
    required = [
        f.name for f in dataclasses.fields(CharucoBoardSpec) if f.default is dataclasses.MISSING
    ]
    missing = [k for k in required + ["T_world_board"] if k not in table]
    if missing:
        raise CalibrationError(f"{path}: [board] misses {missing} (keys: {valid})")
    try:
        return CharucoBoardSpec(**table)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: {exc}") from None


def read_image(path: str | Path) -> np.ndarray:
    """An image file as RGB uint8; :class:`CalibrationError` if it cannot be read."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise CalibrationError(f"cannot read image {path} (missing, or not an image OpenCV reads)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


@dataclass(frozen=True)
class Detection:
    """One image's ChArUco corners: board-frame points (m) and their pixels."""

    object_points: np.ndarray
    image_points: np.ndarray
    markers: int


def detect(spec: CharucoBoardSpec, image: np.ndarray, source: str = "image") -> Detection:
    """The board's corners in ``image`` (RGB, BGR or grey uint8); :class:`CalibrationError`
    when fewer than :data:`MIN_CORNERS` are found."""
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    board = spec.board
    corners, ids, _marker_corners, marker_ids = cv2.aruco.CharucoDetector(board).detectBoard(grey)
    markers = 0 if marker_ids is None else len(marker_ids)
    found = 0 if ids is None else len(ids)
    if found < MIN_CORNERS:
        raise CalibrationError(
            f"{source}: ChArUco board not found ({markers} of {len(board.getIds())} markers "
            f"and {found} corners seen, need {MIN_CORNERS} corners); check the board spec "
            f"({spec.squares_x}x{spec.squares_y} squares, {spec.dictionary}), focus and lighting"
        )
    obj, img = board.matchImagePoints(corners, ids)
    return Detection(obj.reshape(-1, 3), img.reshape(-1, 2), markers)


def estimate_intrinsics(
    spec: CharucoBoardSpec, images: Sequence[np.ndarray]
) -> tuple[CameraIntrinsics, np.ndarray, float]:
    """Intrinsics, distortion coefficients and RMS reprojection error (px) from at least
    :data:`MIN_INTRINSICS_VIEWS` views of the board (anywhere: its pose is not used)."""
    if len(images) < MIN_INTRINSICS_VIEWS:
        raise CalibrationError(
            f"estimating intrinsics needs at least {MIN_INTRINSICS_VIEWS} views of the board, "
            f"got {len(images)}; or give the intrinsics (fx, fy, cx, cy)"
        )
    sizes = {im.shape[:2] for im in images}
    if len(sizes) != 1:
        raise CalibrationError(f"intrinsics views differ in size: {sorted(sizes)}")
    height, width = sizes.pop()
    found = [detect(spec, im, f"intrinsics view {i}") for i, im in enumerate(images)]
    rms, K, dist, _r, _t = cv2.calibrateCamera(
        [d.object_points.astype(np.float32) for d in found],
        [d.image_points.astype(np.float32) for d in found],
        (width, height),
        None,
        None,
    )
    intrinsics = CameraIntrinsics(
        float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height
    )
    return intrinsics, dist.ravel(), float(rms)


@dataclass(frozen=True)
class Calibration:
    """A calibrated camera and how well its pose explains the corners."""

    camera: PlacedCamera
    reprojection_px: float
    corners: int


def calibrate(
    name: str,
    spec: CharucoBoardSpec,
    images: Sequence[np.ndarray],
    intrinsics: CameraIntrinsics,
    distortion: np.ndarray | None = None,
) -> Calibration:
    """Camera ``name``'s pose in the world frame from ``images`` of the board at its pose."""
    if not images:
        raise CalibrationError(f"camera {name!r}: no images of the board")
    for i, im in enumerate(images):
        if im.shape[:2] != (intrinsics.height, intrinsics.width):
            raise CalibrationError(
                f"camera {name!r}: image {i} is {im.shape[1]}x{im.shape[0]}, the intrinsics "
                f"are for {intrinsics.width}x{intrinsics.height}"
            )
    found = [detect(spec, im, f"camera {name!r} image {i}") for i, im in enumerate(images)]
    obj = np.concatenate([d.object_points for d in found]).astype(np.float64)
    img = np.concatenate([d.image_points for d in found]).astype(np.float64)
    dist = np.zeros(5) if distortion is None else np.asarray(distortion, dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, intrinsics.matrix, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError(f"camera {name!r}: no camera pose fits the board's corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, intrinsics.matrix, dist, rvec, tvec)
    projected, _ = cv2.projectPoints(obj, rvec, tvec, intrinsics.matrix, dist)
    error = float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - img) ** 2, axis=1))))
    T_camera_board = np.eye(4)
    T_camera_board[:3, :3] = cv2.Rodrigues(rvec)[0]
    T_camera_board[:3, 3] = tvec.ravel()
    T_world_camera = np.asarray(spec.T_world_board) @ np.linalg.inv(T_camera_board)
    camera = PlacedCamera(name, tuple(map(tuple, T_world_camera)), intrinsics=intrinsics)
    return Calibration(camera, error, len(obj))


def _number(v: float) -> str:
    return f"{v:.6f}".rstrip("0").rstrip(".") if v != 0 else "0.0"


def rig_table(calibration: Calibration) -> str:
    """The rig file's ``[cameras.NAME]`` pose and intrinsics keys, as TOML text."""
    camera = calibration.camera
    k = camera.intrinsics
    T = np.asarray(camera.T_world_camera)
    rows = ",\n    ".join("[" + ", ".join(_number(v) for v in row) + "]" for row in T)
    yaw, pitch, roll = _ypr_deg(camera.R_world_optical)
    lines = [
        f"[cameras.{camera.name}]",
        "# add the camera's LeRobot keys (type, index_or_path / serial_number_or_name, fps)",
        f"# calibrated on {calibration.corners} ChArUco corners, "
        f"reprojection RMS {calibration.reprojection_px:.2f} px",
        f"# at {_number(T[0, 3])}, {_number(T[1, 3])}, {_number(T[2, 3])} m; optical frame "
        f"yaw/pitch/roll {yaw:.1f}/{pitch:.1f}/{roll:.1f} deg (ZYX)",
        "# T_world_camera: the camera's optical frame (x right, y down, z forward) in the world",
        f"T_world_camera = [\n    {rows},\n]",
    ]
    if k is not None:
        lines += [
            f"width = {k.width}",
            f"height = {k.height}",
            f"fx = {_number(k.fx)}",
            f"fy = {_number(k.fy)}",
            f"cx = {_number(k.cx)}",
            f"cy = {_number(k.cy)}",
        ]
    return "\n".join(lines) + "\n"


def _ypr_deg(R: np.ndarray) -> tuple[float, float, float]:
    yaw = math.atan2(R[1, 0], R[0, 0])
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    roll = math.atan2(R[2, 1], R[2, 2])
    return math.degrees(yaw), math.degrees(pitch), math.degrees(roll)
