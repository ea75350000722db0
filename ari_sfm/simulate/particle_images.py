"""Particle images: Gaussian particle images, plain or with a real tank's look.

:func:`render_particle_image` draws pixel-integrated Gaussian images (e^-2
diameter d, sigma = d / 4) on a flat background with Gaussian noise, 8-bit:
the plain frames of ``simulate particles``. :func:`render_tank_frame` draws
the same particle images as a camera behind a real tank records them
(:class:`TankLook`): an uneven background (a gradient and broad lobes of
light), bright reflection streaks (a glass edge, a wall), a few big bright
blobs (bubbles, reflections off the model), glare (a wall lit near
saturation, with streaky texture), particles of varying brightness and size,
faint sharp specks (seeding out of the light sheet, out of focus: 1-2 px,
fainter than the particles) and dust (faint blurred discs), shot and read
noise, optional hot pixels, 8- or 16-bit. Grey levels of :class:`TankLook`
are on the 8-bit scale (255 full scale); a 16-bit frame holds the same scene
times 257 (65535 full scale), quantised in 16 bits. The defaults follow
OpenPTV's test_cavity images (1280 x 1024, 8-bit).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

FULL_SCALE = {8: 255.0, 16: 65535.0}


def add_gaussian_images(img: np.ndarray, uv: np.ndarray, peak: np.ndarray | float,
                        sigma: np.ndarray | float) -> None:
    """Add pixel-integrated Gaussian images to an image, in place.

    Args:
        img: the (h, w) float image, modified in place.
        uv: the centres (N, 2), OpenCV pixel convention.
        peak: the peak of the continuous profile (grey levels), scalar or (N,).
        sigma: the Gaussian's sigma (px), scalar or (N,).
    """
    from scipy.special import erf

    h, w = img.shape
    uv = np.asarray(uv, float).reshape(-1, 2)
    n = len(uv)
    peak = np.broadcast_to(np.asarray(peak, float), (n,))
    sig = np.asarray(sigma, float)
    r = int(math.ceil(3 * float(sig.max(initial=0.0)))) + 1
    s2 = math.sqrt(2.0) * (sig if sig.ndim == 0 else sig[:, None])
    offs = np.arange(-r, r + 1)
    cu, cv = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)

    def integrated(centres: np.ndarray, pix: np.ndarray) -> np.ndarray:
        return 0.5 * (erf((pix + 0.5 - centres[:, None]) / s2) - erf((pix - 0.5 - centres[:, None]) / s2))

    xs = cu[:, None] + offs  # (N, 2r+1)
    ys = cv[:, None] + offs
    gx = integrated(uv[:, 0], xs)
    gy = integrated(uv[:, 1], ys)
    norm = 2.0 * math.pi * sig * sig  # peak of the integrated profile ~ 1 / norm per unit flux
    scale = peak * norm
    vals = scale[:, None, None] * gy[:, :, None] * gx[:, None, :]
    X = np.broadcast_to(xs[:, None, :], vals.shape)
    Y = np.broadcast_to(ys[:, :, None], vals.shape)
    ok = (X >= 0) & (X < w) & (Y >= 0) & (Y < h)
    np.add.at(img, (Y[ok], X[ok]), vals[ok])


def render_particle_image(uv: np.ndarray, image_size: tuple[int, int], diameter_px: float,
                          peak: np.ndarray | float = 180.0, background: float = 10.0, noise_sigma: float = 2.0,
                          rng: np.random.Generator | None = None) -> np.ndarray:
    """Render an 8-bit image of pixel-integrated Gaussian particle images plus Gaussian camera noise.

    Args:
        uv: the particle centres (N, 2), OpenCV pixel convention.
        image_size: the image size (w, h) in px.
        diameter_px: the particle images' e^-2 diameter (px); sigma = diameter / 4.
        peak: the peak of each profile (grey levels), scalar or (N,).
        background: the flat background (grey levels).
        noise_sigma: the standard deviation of the noise (grey levels); 0 for none.
        rng: the random generator (default: seeded with 0).

    Returns:
        The (h, w) uint8 image.
    """
    w, h = image_size
    img = np.full((h, w), float(background))
    add_gaussian_images(img, uv, peak, diameter_px / 4.0)
    if noise_sigma > 0:
        img += (rng or np.random.default_rng(0)).normal(0.0, noise_sigma, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class TankLook:
    """How a frame of a real tank looks. Grey levels on the 8-bit scale (255 full scale)."""

    bit_depth: int = 8  # 8 or 16 (16: the same scene x 257, quantised in 16 bits)
    background: tuple[float, float] = (6.0, 40.0)  # the uneven background spans this range
    read_noise: float = 1.0  # Gaussian noise, grey levels
    shot_gain: float = 0.02  # shot noise: variance += shot_gain x signal (grey levels)
    peak: tuple[float, float] = (30.0, 220.0)  # particle peaks above the background, log-uniform in this range
    diameter_spread: float = 0.25  # particle diameters uniform in d (1 -/+ spread)
    streaks: int = 1  # bright reflection streaks across the frame
    streak_peak: float = 90.0  # their brightness above the background
    streak_width_px: float = 5.0  # their e^-2 width
    blobs: int = 3  # big bright blobs
    blob_radius_px: tuple[float, float] = (8.0, 30.0)
    blob_peak: float = 400.0  # above full scale: saturated cores
    hot_pixels: float = 0.0  # fraction of the pixels stuck at full scale
    specks: float = 0.01  # faint sharp specks per pixel (seeding out of the light, out of focus)
    speck_peak: tuple[float, float] = (6.0, 25.0)  # their peaks, log-uniform
    speck_sigma_px: tuple[float, float] = (0.3, 0.45)  # their sigmas: 1-2 px images
    dust: float = 2e-5  # dust per pixel: faint blurred discs
    dust_radius_px: tuple[float, float] = (3.0, 8.0)
    dust_peak: tuple[float, float] = (8.0, 30.0)
    glare: int = 1  # glare bands (a glass wall lit near saturation), near vertical
    glare_width_px: tuple[float, float] = (20.0, 60.0)
    glare_level: tuple[float, float] = (170.0, 245.0)  # their brightness above the background, with texture


@dataclass(frozen=True)
class TankFrame:
    """A rendered frame and what its particle images are."""

    image: np.ndarray  # (h, w) uint8 or uint16
    peak: np.ndarray  # (N,) each particle image's peak above the background, in the image's units
    diameter_px: np.ndarray  # (N,) e^-2 diameters
    covered: np.ndarray  # (N,) bool: under a blob, a streak's core or glare (brighter than the particle's peak there)
    specks: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))  # (S, 2) the specks' centres
    dust: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))  # (D, 3) the dust discs' u, v, radius


def render_tank_frame(uv: np.ndarray, image_size: tuple[int, int], diameter_px: float, look: TankLook = TankLook(),
                      rng: np.random.Generator | None = None, peak: np.ndarray | None = None,
                      diameter_px_each: np.ndarray | None = None) -> TankFrame:
    """Render particle images as a camera behind a real tank records them.

    Each particle's peak and diameter are drawn from ``look`` unless given (give them to render the
    same particle seen by several cameras).

    Args:
        uv: the particle centres (N, 2), OpenCV pixel convention.
        image_size: the image size (w, h) in px.
        diameter_px: the mean e^-2 diameter (px) the diameters are drawn around.
        look: how the frame looks (clutter, noise, bit depth).
        rng: the random generator (default: seeded with 0).
        peak: each particle's peak above the background (8-bit grey levels), scalar or (N,); None to draw it.
        diameter_px_each: each particle's e^-2 diameter (px), scalar or (N,); None to draw it.

    Returns:
        The frame and what its particle images are.

    Raises:
        ValueError: if ``look.bit_depth`` is not 8 or 16.
    """
    if look.bit_depth not in FULL_SCALE:
        raise ValueError(f"bit_depth must be 8 or 16 (got {look.bit_depth})")
    rng = rng or np.random.default_rng(0)
    w, h = image_size
    uv = np.asarray(uv, float).reshape(-1, 2)
    n = len(uv)
    lo, hi = look.peak
    drawn_peak = np.exp(rng.uniform(math.log(lo), math.log(hi), n))
    drawn_diameter = diameter_px * rng.uniform(1.0 - look.diameter_spread, 1.0 + look.diameter_spread, n)
    peak = drawn_peak if peak is None else np.broadcast_to(np.asarray(peak, float), (n,))
    diameter = (drawn_diameter if diameter_px_each is None
                else np.broadcast_to(np.asarray(diameter_px_each, float), (n,)))
    scene = _uneven_background((h, w), look.background, rng)
    clutter = np.zeros((h, w))
    for _ in range(look.streaks):
        _add_streak(clutter, look.streak_peak, look.streak_width_px, rng)
    for _ in range(look.blobs):
        _add_blob(clutter, look.blob_radius_px, look.blob_peak, rng)
    for _ in range(look.glare):
        _add_glare(clutter, look.glare_width_px, look.glare_level, rng)
    iu = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
    iv = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
    covered = clutter[iv, iu] > peak if n else np.zeros(0, bool)
    scene += clutter
    add_gaussian_images(scene, uv, peak, diameter / 4.0)
    specks = _add_specks(scene, look, rng)
    dust = _add_dust(scene, look, rng)
    variance = look.read_noise ** 2 + look.shot_gain * np.maximum(scene, 0.0)
    scene += rng.normal(0.0, 1.0, scene.shape) * np.sqrt(variance)
    if look.hot_pixels > 0:
        hot = rng.random(scene.shape) < look.hot_pixels
        scene[hot] = 255.0
    unit = FULL_SCALE[look.bit_depth] / 255.0
    image = np.clip(np.rint(scene * unit), 0, FULL_SCALE[look.bit_depth])
    image = image.astype(np.uint8 if look.bit_depth == 8 else np.uint16)
    return TankFrame(image=image, peak=peak * unit, diameter_px=diameter, covered=covered, specks=specks, dust=dust)


def _add_specks(img: np.ndarray, look: TankLook, rng: np.random.Generator) -> np.ndarray:
    """Faint sharp specks (seeding out of the light sheet, out of focus): 1-2 px images, peaks and sigmas
    log-uniform and uniform in the look's ranges, uniform over the frame. Returns their centres."""
    h, w = img.shape
    n = int(rng.poisson(look.specks * h * w)) if look.specks > 0 else 0
    uv = rng.uniform([-0.5, -0.5], [w - 0.5, h - 0.5], (n, 2))
    lo, hi = look.speck_peak
    peak = np.exp(rng.uniform(math.log(lo), math.log(hi), n))
    add_gaussian_images(img, uv, peak, rng.uniform(*look.speck_sigma_px, n))
    return uv


def _add_dust(img: np.ndarray, look: TankLook, rng: np.random.Generator) -> np.ndarray:
    """Dust on the window, out of focus: faint discs with soft edges (super-Gaussian), a few per frame.
    Returns (D, 3) their centres and radii."""
    h, w = img.shape
    n = int(rng.poisson(look.dust * h * w)) if look.dust > 0 else 0
    out = np.empty((n, 3))
    for k in range(n):
        r = rng.uniform(*look.dust_radius_px)
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        out[k] = cx, cy, r
        y0, y1 = max(0, int(cy - 2 * r)), min(h, int(cy + 2 * r) + 1)
        x0, x1 = max(0, int(cx - 2 * r)), min(w, int(cx + 2 * r) + 1)
        if y0 >= y1 or x0 >= x1:
            continue
        y, x = np.mgrid[y0:y1, x0:x1].astype(float)
        rho = np.hypot(x - cx, y - cy) / r
        img[y0:y1, x0:x1] += rng.uniform(*look.dust_peak) * np.exp(-rho ** 4)
    return out


def _add_glare(img: np.ndarray, width_px: tuple[float, float], level: tuple[float, float],
               rng: np.random.Generator) -> None:
    """A glass wall lit near saturation: a near-vertical band (soft edges) at a level in ``level``, with
    streaky texture along it (thin lines, +-15 % of the level) and a brighter core line."""
    h, w = img.shape
    y, x = np.mgrid[0:h, 0:w].astype(float)
    angle = math.radians(rng.uniform(-5.0, 5.0))
    x0 = rng.uniform(0.1 * w, 0.9 * w)
    across = (x - x0 - (y - h / 2) * math.tan(angle)) * math.cos(angle)
    half = 0.5 * rng.uniform(*width_px)
    band = 1.0 / (1.0 + np.exp(np.minimum((np.abs(across) - half) / 2.0, 50.0)))  # soft-edged band
    texture = np.zeros_like(across)
    for _ in range(6):  # thin streaks along the wall
        c = rng.uniform(-half, half)
        texture += rng.uniform(-0.15, 0.15) * np.exp(-0.5 * ((across - c) / rng.uniform(0.7, 2.0)) ** 2)
    img += rng.uniform(*level) * band * (1.0 + texture)


def _uneven_background(shape: tuple[int, int], span: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """A smooth field spanning ``span``: a tilted plane and a few broad lobes of light."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(float)
    size = float(max(h, w))
    field = rng.normal(size=2) @ np.stack([x.ravel(), y.ravel()]) / size
    field = field.reshape(h, w)
    for _ in range(3):
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        s = rng.uniform(0.15, 0.4) * size
        field += rng.uniform(0.5, 1.5) * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * s * s))
    field -= field.min()
    top = field.max()
    return span[0] + (span[1] - span[0]) * (field / top if top > 0 else field)


def _add_streak(img: np.ndarray, peak: float, width_px: float, rng: np.random.Generator) -> None:
    """A bright line across the frame (near vertical, like a wall's edge), brightness varying along it."""
    h, w = img.shape
    y, x = np.mgrid[0:h, 0:w].astype(float)
    angle = math.radians(rng.uniform(-15.0, 15.0))
    x0 = rng.uniform(0.1 * w, 0.9 * w)
    dist = (x - x0 - (y - h / 2) * math.tan(angle)) * math.cos(angle)
    along = 0.6 + 0.4 * np.sin(2 * math.pi * y / h * rng.uniform(0.5, 2.0) + rng.uniform(0, 2 * math.pi))
    img += peak * along * np.exp(-2.0 * dist ** 2 / (0.25 * width_px ** 2))


def _add_blob(img: np.ndarray, radius_px: tuple[float, float], peak: float, rng: np.random.Generator) -> None:
    """A big bright blob with a soft edge (a super-Gaussian disc)."""
    h, w = img.shape
    r = rng.uniform(*radius_px)
    cx, cy = rng.uniform(0, w), rng.uniform(0, h)
    y0, y1 = max(0, int(cy - 3 * r)), min(h, int(cy + 3 * r) + 1)
    x0, x1 = max(0, int(cx - 3 * r)), min(w, int(cx + 3 * r) + 1)
    if y0 >= y1 or x0 >= x1:
        return
    y, x = np.mgrid[y0:y1, x0:x1].astype(float)
    rho = np.hypot(x - cx, y - cy) / r
    img[y0:y1, x0:x1] += peak * rng.uniform(0.5, 1.0) * np.exp(-rho ** 4)
