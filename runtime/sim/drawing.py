"""Drawing one rendered photo: a board's printed paper mapped onto its plane (4x supersampled,
box-filtered, depth-tested), the background clutter and the sensor (vignetting, optical blur,
read and shot noise). Pixels and frames as in ``render``."""

from __future__ import annotations

import cv2
import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.formats.rig import Board, charuco_board
from dimenet.runtime.geometry import rescaled_px, rvec_to_matrix

MARGIN_SQUARES = 0.5  # white paper around the printed pattern, in squares


SUPERSAMPLE = 4  # board patches are drawn at 4x4 samples per pixel, then box-filtered


MAX_TEXELS_PER_SQUARE = 256


CHARUCO_SIZE_TRIES = 4  # texel counts tried (2 apart) when OpenCV refuses to draw a ChArUco board at one


def paper_rect_mm(board: Board) -> tuple[float, float, float, float]:
    """The board's paper in its own frame (mm): x0, y0, x1, y1 of the printed pattern plus the margin."""
    nx, ny = board.inner_corners
    s = board.square_mm
    m = MARGIN_SQUARES * s
    return -s - m, -s - m, nx * s + m, ny * s + m


def pattern_image(board: Board, texels_per_square: int) -> tuple[int, np.ndarray]:
    """The texels per square used and the (h, w) uint8 paper image: the printed pattern (0 black, 255
    white) with the white margin.

    Texel (u, v) has its centre at board (x0 + (u + 0.5)·t, y0 + (v + 0.5)·t) mm, t = square / texels,
    (x0, y0) the paper corner (``paper_rect_mm``). ChArUco boards use OpenCV's CharucoBoard image
    (square (0, 0) black, markers in the white squares, ids from ``first_id``); OpenCV refuses some
    sizes (its marker rounding overflows the square), so the next even count it draws is used.
    """
    nx, ny = board.inner_corners
    for tps in range(texels_per_square, texels_per_square + 2 * CHARUCO_SIZE_TRIES, 2):
        margin = tps // 2
        size = ((nx + 1) * tps + 2 * margin, (ny + 1) * tps + 2 * margin)
        if board.aruco is None:
            i = (np.arange(size[0]) - margin) // tps
            j = (np.arange(size[1]) - margin) // tps
            black = (i[None, :] + j[:, None]) % 2 == 0
            inside = ((i >= 0) & (i <= nx))[None, :] & ((j >= 0) & (j <= ny))[:, None]
            return tps, np.where(black & inside, 0, 255).astype(np.uint8)
        try:
            return tps, charuco_board(board).generateImage(size, marginSize=margin, borderBits=1)
        except cv2.error:
            continue
    raise InputError(f"OpenCV cannot draw ChArUco board {board.name!r} near {texels_per_square} px per square")


def board_homography(board: Board, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(3, 3) homography from board-plane (x, y) mm to image px: K·[r1 r2 t] of the board in {C}."""
    R_cw = rvec_to_matrix(rvec)
    R_cb = R_cw @ board.rotation()
    t_cb = R_cw @ np.asarray(board.tvec_mm) + tvec
    return K @ np.column_stack([R_cb[:, 0], R_cb[:, 1], t_cb])


def texels_per_square(board: Board, H: np.ndarray) -> int:
    """Texels per square (even) so that a texel is about one supersample at the board's largest scale."""
    nx, ny = board.inner_corners
    s = board.square_mm
    j, i = np.mgrid[-1 : ny + 1, -1 : nx + 1]
    grid = cv2.perspectiveTransform(np.stack([i * s, j * s], -1).reshape(-1, 1, 2).astype(np.float64), H)
    grid = grid.reshape(ny + 2, nx + 2, 2)
    step = max(
        np.linalg.norm(np.diff(grid, axis=0), axis=-1).max(), np.linalg.norm(np.diff(grid, axis=1), axis=-1).max()
    )
    return int(min(MAX_TEXELS_PER_SQUARE, 2 * np.ceil(SUPERSAMPLE * step / 2)))


def inverse_depth(board: Board, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, lo, hi) -> np.ndarray:
    """(h, w) float32 1/z (1/mm) of the board's plane at the pixels [lo, hi) (x, y px): affine in the pixel."""
    R_cw = rvec_to_matrix(rvec)
    normal = R_cw @ board.normal()
    a = normal @ np.linalg.inv(K) / (normal @ (R_cw @ np.asarray(board.tvec_mm) + tvec))
    u = np.arange(lo[0], hi[0], dtype=np.float32)
    v = np.arange(lo[1], hi[1], dtype=np.float32)
    return (np.float32(a[0]) * u[None, :] + np.float32(a[1]) * v[:, None] + np.float32(a[2])).astype(np.float32)


def draw_board(
    canvas: np.ndarray,
    zbuf: np.ndarray,
    board: Board,
    K: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    white: float,
    black: float,
) -> None:
    """Composite the board's paper onto ``canvas`` (h, w, 3) float32 in place, anti-aliased, depth-tested.

    ``zbuf`` (h, w) holds the inverse depth (1/mm, 0 = nothing) of what is drawn and is updated;
    ``white``/``black`` are the paper's and the ink's grey levels.
    """
    H = board_homography(board, K, rvec, tvec)
    h_img, w_img = canvas.shape[:2]
    tps, pattern = pattern_image(board, texels_per_square(board, H))
    x0, y0, x1, y1 = paper_rect_mm(board)
    paper = cv2.perspectiveTransform(np.array([[[x0, y0]], [[x1, y0]], [[x1, y1]], [[x0, y1]]]), H).reshape(4, 2)
    lo = np.maximum(np.floor(paper.min(0)) - 2, 0).astype(int)
    hi = np.minimum(np.ceil(paper.max(0)) + 3, [w_img, h_img]).astype(int)
    if np.any(hi <= lo):
        return
    w, h = hi - lo
    t = board.square_mm / tps
    texel_to_board = np.array([[t, 0.0, x0 + 0.5 * t], [0.0, t, y0 + 0.5 * t], [0.0, 0.0, 1.0]])
    ss = SUPERSAMPLE
    shift = lo + rescaled_px(0.0, 1 / ss)  # a sample's px in the image: rescaled by 1 / ss, then shifted to lo
    sample_to_image = np.array([[1 / ss, 0.0, shift[0]], [0.0, 1 / ss, shift[1]], [0.0, 0.0, 1.0]])
    M = np.linalg.inv(sample_to_image) @ H @ texel_to_board
    src = np.dstack([pattern, np.full_like(pattern, 255)])
    warped = cv2.warpPerspective(
        src, M, (ss * w, ss * h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    small = cv2.resize(warped, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    inv = inverse_depth(board, K, rvec, tvec, lo, hi)
    depth = zbuf[lo[1] : hi[1], lo[0] : hi[0]]
    front = (inv > depth).astype(np.float32)[..., None]
    ink, alpha = small[..., 0:1] * front, small[..., 1:2] * front
    depth[alpha[..., 0] > 0] = inv[alpha[..., 0] > 0]
    roi = canvas[lo[1] : hi[1], lo[0] : hi[0]]
    roi *= 1.0 - alpha
    roi += black * alpha + (white - black) * ink


def clutter(size: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """(h, w, 3) float32 background: a smooth colour field with random filled shapes and lines."""
    w, h = size
    field = cv2.resize(rng.uniform(40, 200, (4, 5, 3)).astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)
    img = np.clip(field, 0, 255).astype(np.uint8)
    scale = max(w, h)
    for _ in range(60):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        r = int(rng.uniform(0.005, 0.08) * scale)
        kind = int(rng.integers(4))
        if kind == 0:
            cv2.circle(img, (x, y), r, colour, -1, cv2.LINE_AA)
        elif kind == 1:
            axes = (r, max(1, int(r * rng.uniform(0.2, 1.0))))
            cv2.ellipse(img, (x, y), axes, float(rng.uniform(0, 180)), 0, 360, colour, -1, cv2.LINE_AA)
        elif kind == 2:
            pts = np.array([[x, y]]) + rng.integers(-r, r + 1, (int(rng.integers(3, 7)), 2))
            cv2.fillPoly(img, [pts.astype(np.int32)], colour, cv2.LINE_AA)
        else:
            end = (x + int(rng.integers(-3 * r, 3 * r + 1)), y + int(rng.integers(-3 * r, 3 * r + 1)))
            cv2.line(img, (x, y), end, colour, max(1, r // 8), cv2.LINE_AA)
    return img.astype(np.float32)


def vignetting(size: tuple[int, int], strength: float) -> np.ndarray:
    """(h, w, 1) float32 gain: 1 at the centre, 1 - strength at the image corners (quadratic in radius)."""
    w, h = size
    x = (np.arange(w, dtype=np.float32) - (w - 1) / 2) / (w / 2)
    y = (np.arange(h, dtype=np.float32) - (h - 1) / 2) / (h / 2)
    r2 = (x[None, :] ** 2 + y[:, None] ** 2) / 2.0
    return (1.0 - strength * r2)[..., None]


def sensor(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Radiance (h, w, 3) float32 -> 8-bit photo: vignetting, Gaussian blur, read + shot noise."""
    h, w = img.shape[:2]
    img *= vignetting((w, h), float(rng.uniform(0.15, 0.35)))
    sigma = float(rng.uniform(0.6, 1.1)) * max(w, h) / 4032.0
    img = cv2.GaussianBlur(img, (0, 0), max(sigma, 0.3))
    noise = rng.standard_normal(img.shape, dtype=np.float32)
    img += noise * np.sqrt(np.float32(2.0**2) + np.float32(0.03) * np.maximum(img, 0))
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)
