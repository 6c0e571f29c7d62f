"""The ChArUco board: its description, its image, and its pose in a colour image (OpenCV's aruco module).

    board = CharucoBoardSpec()                              # 7 x 5 squares of 36 mm, 27 mm markers, DICT_4X4_50: A4
    image = board_image(board, px_per_square=100)           # (H, W) uint8, what a printer or the twin's texture shows
    found = detect_board(frame.color, frame.intrinsics, board)   # BoardDetection
    if found.ok:
        found.board_to_camera                               # (4, 4): a point on the board -> the camera's optical frame

The board frame is OpenCV's: origin at the board's top-left outer corner as the image shows it, x along the
squares' rows (``squares_x``), y down the columns, z into the board (away from its printed face); metres.
A detection is refused, with its reason, when it has fewer than ``min_corners`` ChArUco corners, when those
corners lie on one line, or when the pose reprojects worse than ``max_reprojection_px`` (RMS over the corners).
The intrinsics are the frame's (:class:`dssp_data.pointcloud.depth_frame.Intrinsics`, no distortion: colour aligned to
depth carries the depth stream's intrinsics, so the pose is in the depth camera's optical frame — the frame the
point clouds are deprojected in).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np

from dssp_core.errors import ConfigError
from dssp_core.schema import Settings, setting
from dssp_data.pointcloud.depth_frame import Intrinsics

DICTIONARIES = tuple(f"DICT_{n}X{n}_{k}" for n in (4, 5, 6, 7) for k in (50, 100, 250, 1000))
"""The ArUco dictionaries a board may use (OpenCV's predefined ones, by name)."""

MIN_CORNERS = 8
"""ChArUco corners a detection needs: solvePnP takes 4, but with 8 spread over the board one bad corner does not
decide the pose."""

MAX_REPROJECTION_PX = 1.0
"""RMS reprojection error (pixels) above which a detection is refused: sub-pixel corners on a sharp, flat board
reproject to a few tenths of a pixel; a full pixel means blur, a bent board or wrong intrinsics."""


@dataclass(frozen=True)
class CharucoBoardSpec(Settings):
    """A ChArUco board: ``squares_x`` x ``squares_y`` chessboard squares of ``square_m`` metres, an ArUco marker of
    ``marker_m`` in each white square, from ``dictionary``. The default prints on A4 (252 x 180 mm, landscape); a
    ``--board`` file is a JSON object of these fields. Measure the printed square: a printer that scales the page
    scales every translation of the calibration with it."""

    SECTION: ClassVar[str] = "board"

    squares_x: int = setting(7, ge=3, le=30)
    squares_y: int = setting(5, ge=3, le=30)
    square_m: float = setting(0.036, gt=0.004, le=0.5, unit="m")
    marker_m: float = setting(0.027, gt=0.003, le=0.5, unit="m")
    dictionary: str = setting("DICT_4X4_50", choices=DICTIONARIES)

    def validate(self) -> None:
        if self.marker_m >= self.square_m:
            raise ConfigError(
                f"board.marker_m ({self.marker_m:g} m) must be smaller than board.square_m "
                f"({self.square_m:g} m): the marker sits inside a white square"
            )
        markers = self.squares_x * self.squares_y // 2
        size = int(re.fullmatch(r"DICT_\dX\d_(\d+)", self.dictionary).group(1))
        if markers > size:
            raise ConfigError(
                f"board: {self.squares_x} x {self.squares_y} squares need {markers} markers but "
                f"{self.dictionary} has {size}; choose a larger dictionary"
            )

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the squares, metres."""
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    @property
    def centre(self) -> np.ndarray:
        """(3,) the board's centre in the board frame, metres (where residuals are measured)."""
        w, h = self.size_m
        return np.array([w / 2.0, h / 2.0, 0.0])

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board object."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m, dictionary)


def load_board(path) -> CharucoBoardSpec:
    """The board of a ``--board`` JSON file (None: the default A4 board); one-line ConfigError naming the path."""
    return CharucoBoardSpec() if path is None else CharucoBoardSpec.load(path, "board")


def board_image(board: CharucoBoardSpec, px_per_square: int = 100, margin_squares: float = 0.0) -> np.ndarray:
    """(H, W) uint8 image of the board, ``px_per_square`` pixels per square, with a white margin of
    ``margin_squares`` squares on each side (OpenCV's ``generateImage``)."""
    margin = int(round(margin_squares * px_per_square))
    size = (board.squares_x * px_per_square + 2 * margin, board.squares_y * px_per_square + 2 * margin)
    return board.cv_board().generateImage(size, marginSize=margin, borderBits=1)


@dataclass(frozen=True)
class BoardDetection:
    """The board found in one image, or why not.

    ok: a usable pose. reason: why not ("" when ok). corners: ChArUco corners found. board_to_camera: (4, 4) or None.
    reprojection_px: RMS reprojection error of the corners under that pose (NaN without a pose).
    """

    ok: bool
    reason: str
    corners: int
    board_to_camera: np.ndarray | None = None
    reprojection_px: float = float("nan")


def camera_matrix(intrinsics: Intrinsics) -> np.ndarray:
    """(3, 3) pinhole matrix K of ``intrinsics`` (RealSense's ppx/ppy are pixel coordinates as OpenCV's cx/cy)."""
    return np.array([[intrinsics.fx, 0.0, intrinsics.ppx], [0.0, intrinsics.fy, intrinsics.ppy], [0.0, 0.0, 1.0]])


def detect_board(
    color: np.ndarray | None,
    intrinsics: Intrinsics,
    board: CharucoBoardSpec,
    *,
    min_corners: int = MIN_CORNERS,
    max_reprojection_px: float = MAX_REPROJECTION_PX,
) -> BoardDetection:
    """Find ``board`` in ``color`` (H, W, 3) uint8 RGB (or (H, W) grey) and its pose in the camera frame.

    The corners come from OpenCV's ``CharucoDetector`` (markers, then the chessboard corners between them, refined
    to sub-pixel); the pose from ``solvePnP`` on the matched corners (IPPE for a plane, then Levenberg-Marquardt)."""
    if color is None:
        return BoardDetection(False, "the frame has no colour image (open the camera with colour)", 0)
    image = np.asarray(color)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        return BoardDetection(False, f"the colour image must be (H, W, 3) uint8, got {image.dtype} {image.shape}", 0)
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    cv = board.cv_board()
    corners, ids, _, marker_ids = cv2.aruco.CharucoDetector(cv).detectBoard(grey)
    n = 0 if ids is None else len(ids)
    if n < min_corners:
        markers = 0 if marker_ids is None else len(marker_ids)
        return BoardDetection(False, f"{n} board corners found ({markers} markers), {min_corners} needed", n)
    if cv.checkCharucoCornersCollinear(ids):
        return BoardDetection(False, f"the {n} corners found lie on one line", n)
    object_points, image_points = cv.matchImagePoints(corners, ids)
    object_points = object_points.reshape(-1, 3).astype(np.float64)
    image_points = image_points.reshape(-1, 2).astype(np.float64)
    k, dist = camera_matrix(intrinsics), np.zeros(5)
    ok, rvec, tvec = cv2.solvePnP(object_points, image_points, k, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return BoardDetection(False, f"solvePnP found no pose for the {n} corners", n)
    rvec, tvec = cv2.solvePnPRefineLM(object_points, image_points, k, dist, rvec, tvec)
    projected, _ = cv2.projectPoints(object_points, rvec, tvec, k, dist)
    rms = float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - image_points) ** 2, axis=1))))
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.reshape(3)
    if not rms <= max_reprojection_px:
        return BoardDetection(False, f"reprojection error {rms:.2f} px > {max_reprojection_px:g} px", n, pose, rms)
    if pose[2, 3] <= 0:
        return BoardDetection(False, "the pose puts the board behind the camera", n, pose, rms)
    return BoardDetection(True, "", n, pose, rms)
