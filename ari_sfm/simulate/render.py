"""Render synthetic images of a calibration target seen through any camera model.

The camera model enters only as ``pixel_to_target``: a function mapping pixel
coordinates (N, 2) (OpenCV convention: (0, 0) is the centre of the top-left
pixel) to target-plane coordinates (N, 2) in mm, NaN where the ray misses the
plane. A pinhole, a refractive or any other model renders the same way.

Board appearance (the detector relies on it, see :mod:`ari_sfm.detection`):

- checkerboard (``inner_corners`` (cols, rows), square s): squares (i, j),
  i = 0..cols, j = 0..rows, occupy x in [(i-1) s, i s], y in [(j-1) s, j s];
  a square is black iff i + j is even, so the square diagonally outside
  corner 0 is black. A white margin of one square surrounds the squares.
- ChArUco: OpenCV's own board image (``CharucoBoard.generateImage``), whose
  corner (c, r) lies at ((c+1) s, (r+1) s), plus a white margin of one square.
- dot board (``circles``, DATASET_FORMAT 1.1): black discs of ``diameter_mm``
  (default DEFAULT_DOT_FRACTION x spacing) centred on the target points
  (:meth:`~ari_sfm.records.Target.points_3d`) on white, with a white margin of
  one spacing around the dots' bounding box.
- Outside the board the background is grey.
"""
from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

import cv2
import numpy as np

from ari_sfm.detection import charuco_board
from ari_sfm.records import Target

BLACK = 20.0  # grey levels of the print, kept off 0 / 255 so noise does not clip
WHITE = 235.0
BACKGROUND = 128.0
_CHUNK_SAMPLES = 1 << 20  # samples per chunk: ~1M x (2 coords + temporaries) x 8 B, tens of MB
_CHARUCO_PX_PER_SQUARE = 128  # resolution of the board image sampled for ChArUco
DEFAULT_DOT_FRACTION = 0.5  # dot diameter / spacing of a dot board that declares no diameter_mm

PixelToTarget = Callable[[np.ndarray], np.ndarray]


def plane_pixel_to_target(
    K: np.ndarray, world_from_target_R: np.ndarray, world_from_target_t: np.ndarray
) -> PixelToTarget:
    """Make a ``pixel_to_target`` for a plain pinhole camera at the world origin (cam = world).

    The ray K^-1 [u, v, 1] is intersected with the target plane z_target = 0;
    NaN where the ray is parallel to the plane or meets it behind the camera.

    Args:
        K: the 3x3 intrinsic matrix.
        world_from_target_R: the target's rotation (3, 3), target to world.
        world_from_target_t: the target's origin in the world (3,), mm.

    Returns:
        The function from pixels (N, 2) to target-plane coordinates (N, 2), mm.
    """
    K_inv = np.linalg.inv(np.asarray(K, dtype=float))
    R = np.asarray(world_from_target_R, dtype=float)
    t = np.asarray(world_from_target_t, dtype=float).reshape(3)
    normal = R[:, 2]
    offset = float(normal @ t)

    def pixel_to_target(pixels: np.ndarray) -> np.ndarray:
        pixels = np.asarray(pixels, dtype=float).reshape(-1, 2)
        u, v = pixels[:, 0], pixels[:, 1]
        # ray directions K^-1 [u, v, 1] per component (tiny matmuls are slow in numpy)
        rays = [K_inv[k, 0] * u + K_inv[k, 1] * v + K_inv[k, 2] for k in range(3)]
        denom = normal[0] * rays[0] + normal[1] * rays[1] + normal[2] * rays[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = offset / denom
        scale[~(scale > 0)] = np.nan
        d = [rays[k] * scale - t[k] for k in range(3)]  # world point minus the target origin
        out = np.empty((len(pixels), 2))
        for a in range(2):  # R^T (X - t), first two coordinates
            out[:, a] = R[0, a] * d[0] + R[1, a] * d[1] + R[2, a] * d[2]
        return out

    return pixel_to_target


def project_pinhole(K: np.ndarray, world_from_target_R: np.ndarray, world_from_target_t: np.ndarray,
                    xyz: np.ndarray) -> np.ndarray:
    """Project target points with a pinhole camera at the world origin (cam = world).

    Args:
        K: the 3x3 intrinsic matrix.
        world_from_target_R: the target's rotation (3, 3), target to world.
        world_from_target_t: the target's origin in the world (3,), mm.
        xyz: the target points (N, 3), target frame, mm.

    Returns:
        The exact pixels (N, 2).
    """
    X = np.asarray(xyz, dtype=float) @ np.asarray(world_from_target_R, dtype=float).T
    X = X + np.asarray(world_from_target_t, dtype=float).reshape(3)
    x = X @ np.asarray(K, dtype=float).T
    return x[:, :2] / x[:, 2:3]


def render_target(
    target: Target,
    pixel_to_target: PixelToTarget,
    image_size: tuple[int, int],
    supersample: int = 4,
    noise_sigma: float = 1.0,
    seed: int = 0,
    blur_sigma_px: float = 0.0,
    adaptive: bool = True,
) -> np.ndarray:
    """Render the target as a uint8 grayscale image of shape (height, width).

    Each pixel averages ``supersample`` x ``supersample`` samples spread over its area (box
    anti-aliasing; an n-rooks pattern shifted per pixel); then an optional Gaussian blur (optics) and
    Gaussian sensor noise are applied. Samples are evaluated in chunks of rows so memory stays bounded.

    Args:
        target: the calibration target (checkerboard, ChArUco or dot board).
        pixel_to_target: maps pixels (N, 2) to target-plane coordinates (N, 2) in mm, NaN where the ray misses.
        image_size: the image size (width, height).
        supersample: the samples per pixel along each axis (>= 1).
        noise_sigma: the sensor noise's standard deviation (grey levels); 0 for none.
        seed: the noise's random seed.
        blur_sigma_px: the Gaussian blur's sigma (px); 0 for none.
        adaptive: shade the pixel corners first and supersample only pixels within one pixel of a
            corner-value change (the same image for any board whose features span more than about two pixels).

    Returns:
        The (height, width) uint8 image.

    Raises:
        ValueError: if ``supersample`` < 1 or the target's type cannot be rendered.
    """
    width, height = int(image_size[0]), int(image_size[1])
    n = int(supersample)
    if n < 1:
        raise ValueError(f"supersample must be >= 1 (got {supersample})")
    shade = _shader(target)
    sub = _sample_offsets(n)

    def supersampled(centres: np.ndarray) -> np.ndarray:
        """Mean shade of the n x n samples of each pixel centre (P, 2), chunked."""
        out = np.empty(len(centres), dtype=np.float32)
        step = max(1, _CHUNK_SAMPLES // (n * n))
        for k in range(0, len(centres), step):
            c = centres[k : k + step]
            samples = (c[:, None, :] + _shifted(sub, c)).reshape(-1, 2)
            out[k : k + step] = shade(pixel_to_target(samples)).reshape(len(c), n * n).mean(axis=1)
        return out

    if adaptive and n > 1:
        corners = _shade_grid(shade, pixel_to_target, width + 1, height + 1, -0.5)  # (H+1, W+1)
        lo = np.minimum.reduce([corners[:-1, :-1], corners[:-1, 1:], corners[1:, :-1], corners[1:, 1:]])
        hi = np.maximum.reduce([corners[:-1, :-1], corners[:-1, 1:], corners[1:, :-1], corners[1:, 1:]])
        image = lo.copy()
        mixed = cv2.dilate((hi > lo).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        vs, us = np.nonzero(mixed)  # row-major: chunks follow the rows
        image[vs, us] = supersampled(np.stack([us, vs], axis=1).astype(float))
    else:
        vv, uu = np.mgrid[0:height, 0:width]
        image = supersampled(np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)).reshape(height, width)
    if blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), blur_sigma_px)
    if noise_sigma > 0:
        image += np.random.default_rng(seed).normal(0.0, noise_sigma, image.shape).astype(np.float32)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _sample_offsets(n: int) -> np.ndarray:
    """n*n sub-pixel sample offsets (from the pixel centre, in [-0.5, 0.5)) on an n-rooks lattice.

    One sample per cell of an n x n grid, shifted within its cell so that all
    n*n x values (and all y values) differ: an edge aligned with the pixel
    grid is resolved to 1/n^2 px instead of 1/n px.
    """
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    x = (i + (j + 0.5) / n) / n - 0.5
    y = (j + (i + 0.5) / n) / n - 0.5
    return np.stack([x.ravel(), y.ravel()], axis=1)


def _shifted(sub: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """The pattern ``sub`` toroidally shifted within each pixel by a hash of its (integer) centre.

    Any fixed pattern of few samples has edge directions it resolves coarsely,
    which biases whole edges the same way (up to 0.1 px on corners at n = 4);
    a per-pixel shift (Cranley-Patterson rotation) turns that bias into
    pixel-to-pixel noise that the corner refinement averages out. The shift
    depends only on the pixel, so the image does not depend on chunking.
    """
    key = (np.rint(centres[:, 0]).astype(np.int64) * 73856093) ^ (np.rint(centres[:, 1]).astype(np.int64) * 19349663)
    h = key.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    h ^= h >> np.uint64(29)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(32)
    shift = np.stack([(h & np.uint64(0xFFFFFFFF)), h >> np.uint64(32)], axis=1).astype(float) / 2.0**32
    return (sub[None, :, :] + 0.5 + shift[:, None, :]) % 1.0 - 0.5


def _shade_grid(shade: Callable[[np.ndarray], np.ndarray], pixel_to_target: PixelToTarget,
                width: int, height: int, origin: float) -> np.ndarray:
    """Shade one sample at each (origin + u, origin + v) of a width x height grid, chunked by rows."""
    out = np.empty((height, width), dtype=np.float32)
    u = np.arange(width, dtype=float) + origin
    step = max(1, _CHUNK_SAMPLES // width)
    for v0 in range(0, height, step):
        v = np.arange(v0, min(height, v0 + step), dtype=float) + origin
        vv, uu = np.meshgrid(v, u, indexing="ij")
        shaded = shade(pixel_to_target(np.stack([uu.ravel(), vv.ravel()], axis=1)))
        out[v0 : v0 + len(v)] = shaded.reshape(len(v), width)
    return out


def _shader(target: Target) -> Callable[[np.ndarray], np.ndarray]:
    """A function from target coordinates (N, 2) mm (NaN: miss) to grey levels (N,)."""
    if target.type == "checkerboard":
        return _checkerboard_shader(target)
    if target.type == "charuco":
        return _charuco_shader(target)
    if target.type == "circles":
        return _circles_shader(target)
    raise ValueError(f"cannot render a target of type {target.type!r}")


def _checkerboard_shader(target: Target) -> Callable[[np.ndarray], np.ndarray]:
    cols, rows = target.required(target.inner_corners, "inner_corners")
    s = float(target.square_mm)

    def shade(xy: np.ndarray) -> np.ndarray:
        x, y = xy[:, 0], xy[:, 1]
        out = np.full(len(xy), BACKGROUND, dtype=np.float32)
        with np.errstate(invalid="ignore"):
            on_board = (x >= -2 * s) & (x < (cols + 1) * s) & (y >= -2 * s) & (y < (rows + 1) * s)
            out[on_board] = WHITE
            i = np.floor(x / s) + 1  # square index: square i spans [(i-1) s, i s]
            j = np.floor(y / s) + 1
            in_squares = (i >= 0) & (i <= cols) & (j >= 0) & (j <= rows)
        black = in_squares & ((np.nan_to_num(i + j).astype(np.int64) % 2) == 0)
        out[black] = BLACK
        return out

    return shade


@lru_cache(maxsize=4)
def _charuco_image(squares: tuple[int, int], square_mm: float, marker_mm: float, dictionary: str) -> np.ndarray:
    board = charuco_board(squares, square_mm, marker_mm, dictionary)
    p = _CHARUCO_PX_PER_SQUARE
    img = board.generateImage((squares[0] * p, squares[1] * p), marginSize=0, borderBits=1)
    return (BLACK + (WHITE - BLACK) * (img.astype(np.float32) / 255.0)).astype(np.float32)


def _charuco_shader(target: Target) -> Callable[[np.ndarray], np.ndarray]:
    squares = target.required(target.squares, "squares")
    s = float(target.square_mm)
    board_img = _charuco_image(squares, s, float(target.required(target.marker_mm, "marker_mm")),
                               str(target.dictionary))
    h, w = board_img.shape
    scale = _CHARUCO_PX_PER_SQUARE / s  # board-image pixels per mm

    def shade(xy: np.ndarray) -> np.ndarray:
        x, y = xy[:, 0], xy[:, 1]
        out = np.full(len(xy), BACKGROUND, dtype=np.float32)
        with np.errstate(invalid="ignore"):
            on_board = (x >= -s) & (x < (squares[0] + 1) * s) & (y >= -s) & (y < (squares[1] + 1) * s)
            out[on_board] = WHITE
            # board-image pixel k covers [k, k+1) / scale mm: its centre is at (k + 0.5) / scale
            px, py = x * scale - 0.5, y * scale - 0.5
            inside = (px > -0.5) & (px < w - 0.5) & (py > -0.5) & (py < h - 0.5)
        px, py = np.clip(px[inside], 0, w - 1), np.clip(py[inside], 0, h - 1)
        x0 = np.minimum(np.floor(px).astype(np.int64), w - 2)
        y0 = np.minimum(np.floor(py).astype(np.int64), h - 2)
        fx, fy = (px - x0).astype(np.float32), (py - y0).astype(np.float32)
        top = board_img[y0, x0] * (1 - fx) + board_img[y0, x0 + 1] * fx
        bottom = board_img[y0 + 1, x0] * (1 - fx) + board_img[y0 + 1, x0 + 1] * fx
        out[inside] = top * (1 - fy) + bottom * fy
        return out

    return shade


def dot_diameter_mm(target: Target) -> float:
    """The printed dot diameter of a dot board: ``diameter_mm``, else DEFAULT_DOT_FRACTION x spacing."""
    if target.diameter_mm is not None:
        return float(target.diameter_mm)
    return DEFAULT_DOT_FRACTION * float(target.spacing_mm)


def _circles_shader(target: Target) -> Callable[[np.ndarray], np.ndarray]:
    """Exact discs: a sample is black iff it lies within the dot radius of its nearest dot centre.

    The diameter is below the spacing, so the nearest dot is in row round(y / s)
    and, in that row, at column round((x / s - offset) / step) (asymmetric
    layout: step 2, offset r % 2; symmetric: step 1, offset 0).
    """
    cols, rows = target.required(target.circle_grid, "circle_grid")
    s = float(target.spacing_mm)
    radius = 0.5 * dot_diameter_mm(target)
    asymmetric = target.layout == "asymmetric"
    step = 2.0 if asymmetric else 1.0
    width = ((2 * (cols - 1) + (1 if rows > 1 else 0)) if asymmetric else (cols - 1)) * s

    def shade(xy: np.ndarray) -> np.ndarray:
        x, y = xy[:, 0], xy[:, 1]
        out = np.full(len(xy), BACKGROUND, dtype=np.float32)
        with np.errstate(invalid="ignore"):
            on_board = (x >= -s) & (x <= width + s) & (y >= -s) & (y <= (rows - 1) * s + s)
            out[on_board] = WHITE
            r = np.rint(y / s)
            offset = np.where(np.mod(r, 2) == 1, 1.0, 0.0) if asymmetric else 0.0
            c = np.rint((x / s - offset) / step)
            inside = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
            dx = x - (c * step + offset) * s
            dy = y - r * s
            dot = inside & (dx * dx + dy * dy <= radius * radius)
        out[dot] = BLACK
        return out

    return shade


def add_discs(image: np.ndarray, centres: np.ndarray, diameters_px: np.ndarray | float, peak: np.ndarray | float,
              supersample: int = 5) -> np.ndarray:
    """Add uniformly bright discs to an image (the dots of a 3D calibration body seen from afar).

    Disc k adds ``peak[k]`` grey levels where it covers a pixel wholly; pixels on its edge get the
    covered fraction.

    Args:
        image: the (height, width) image; not modified.
        centres: the disc centres (N, 2), OpenCV pixels.
        diameters_px: the disc diameters (px), scalar or (N,).
        peak: the grey levels each disc adds, scalar or (N,).
        supersample: the samples per pixel along each axis for the covered fraction.

    Returns:
        A new float64 (height, width) array.
    """
    out = np.array(image, dtype=np.float64)
    h, w = out.shape
    centres = np.asarray(centres, float).reshape(-1, 2)
    diameters = np.broadcast_to(np.asarray(diameters_px, float), (len(centres),))
    peaks = np.broadcast_to(np.asarray(peak, float), (len(centres),))
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    for (u, v), d, p in zip(centres, diameters, peaks):
        r = 0.5 * d
        x0, x1 = max(0, int(np.floor(u - r - 1))), min(w, int(np.ceil(u + r + 2)))
        y0, y1 = max(0, int(np.floor(v - r - 1))), min(h, int(np.ceil(v + r + 2)))
        if x0 >= x1 or y0 >= y1:
            continue
        ys = (np.arange(y0, y1)[:, None] + sub[None, :]).reshape(-1)  # sample rows
        xs = (np.arange(x0, x1)[:, None] + sub[None, :]).reshape(-1)
        inside = ((xs[None, :] - u) ** 2 + (ys[:, None] - v) ** 2 <= r * r).astype(float)
        cover = inside.reshape(y1 - y0, supersample, x1 - x0, supersample).mean(axis=(1, 3))
        out[y0:y1, x0:x1] += p * cover
    return out
