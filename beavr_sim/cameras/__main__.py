"""``python -m beavr_sim.cameras calibrate|board``: a real camera's pose (and intrinsics) from
images of a ChArUco board at a known world pose, written as a rig file's ``[cameras.NAME]``
keys; and the board's printable image. See :mod:`beavr_sim.cameras.calibrate` and
docs/cameras.md ("Calibrating a twin camera to a real one").

    python -m beavr_sim.cameras board --board board.toml --out board.png
    python -m beavr_sim.cameras calibrate --board board.toml --camera front \\
        --images front_*.png (--intrinsics FX,FY,CX,CY | --intrinsics-images views/*.png)

Errors (the board not found, bad files) are one line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from beavr_sim.cameras.calibrate import (
    CharucoBoardSpec,
    calibrate,
    estimate_intrinsics,
    load_board,
    read_image,
    rig_table,
)
from beavr_sim.cameras.errors import CalibrationError
from beavr_sim.envs.camera_pose import CameraIntrinsics

EXIT_ERROR = 2


def _intrinsics(text: str, width: int, height: int) -> CameraIntrinsics:
    parts = text.split(",")
    try:
        fx, fy, cx, cy = (float(p) for p in parts)
    except ValueError:
        raise CalibrationError(f"--intrinsics {text!r}: expected FX,FY,CX,CY in pixels") from None
    return CameraIntrinsics(fx, fy, cx, cy, width, height)


def _calibrate(args: argparse.Namespace) -> str:
    board = load_board(args.board)
    images = [read_image(p) for p in args.images]
    height, width = images[0].shape[:2]
    distortion = None
    if args.intrinsics is not None:
        intrinsics = _intrinsics(args.intrinsics, width, height)
    elif args.intrinsics_images:
        views = [read_image(p) for p in args.intrinsics_images]
        intrinsics, distortion, rms = estimate_intrinsics(board, views)
        print(f"intrinsics from {len(views)} views: RMS {rms:.2f} px", file=sys.stderr)
    else:
        raise CalibrationError(
            "give the camera's intrinsics: --intrinsics FX,FY,CX,CY or "
            "--intrinsics-images (at least 3 views of the board, anywhere)"
        )
    result = calibrate(args.camera, board, images, intrinsics, distortion)
    return rig_table(result)


def _board(board: CharucoBoardSpec, px_per_square: int, out: Path) -> None:
    image = np.pad(board.image(px_per_square), px_per_square // 2, constant_values=255)
    if not cv2.imwrite(str(out), image):
        raise CalibrationError(f"cannot write {out}")
    print(
        f"{out}: {board.squares_x}x{board.squares_y} squares of {board.square_m * 1e3:g} mm "
        f"when printed at {px_per_square / (board.square_m * 1e3):.2f} px/mm "
        "(measure a square after printing)",
        file=sys.stderr,
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m beavr_sim.cameras", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("calibrate", help="a camera's pose from images of a ChArUco board")
    c.add_argument("--board", type=Path, required=True, help="board TOML ([board] table)")
    c.add_argument("--camera", required=True, help="the camera's NAME in the rig file")
    c.add_argument("--images", nargs="+", required=True, help="images with the board at its pose")
    c.add_argument("--intrinsics", default=None, help="FX,FY,CX,CY in pixels at the image size")
    c.add_argument(
        "--intrinsics-images", nargs="+", default=None, help="3+ views of the board, anywhere"
    )
    c.add_argument("--out", type=Path, default=None, help="write the table here (default stdout)")
    b = sub.add_parser("board", help="the board's printable image")
    b.add_argument("--board", type=Path, required=True, help="board TOML ([board] table)")
    b.add_argument("--out", type=Path, required=True, help="image file (.png)")
    b.add_argument("--px-per-square", type=int, default=200)
    args = parser.parse_args(argv)
    try:
        if args.command == "board":
            _board(load_board(args.board), args.px_per_square, args.out)
            return 0
        table = _calibrate(args)
    except CalibrationError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except ValueError as exc:  # intrinsics out of range
        print(f"error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return EXIT_ERROR
    if args.out is None:
        print(table, end="")
    else:
        args.out.write_text(table)
        print(f"{args.out}: [cameras.{args.camera}] written", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
