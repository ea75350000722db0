"""Images of a 3D calibration body in a water tank, as a PTV lab takes them: bright dots seen through a flat
wall, with what else such an image shows (particles in the water, a wall's bright streak, glare, a faint
reflection of the dots, a stray dot beside a body dot).

The body (:func:`cavity_body`) is OpenPTV test_cavity's: 73 points on five rows at z = 8, 0, -8, 0, 8 mm.
The camera (:func:`cavity_view`) looks at it as test_cavity's first camera does (about 570 mm away,
through a 6 mm wall 125 mm before the body, water behind); the dots are projected with the exact Snell
model (:class:`~ari_sfm.models.exact.ExactModel`), so the true pixels are exact.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ari_sfm.geometry import Pose
from ari_sfm.models.exact import ExactModel
from ari_sfm.models.pinhole import PinholeModel
from ari_sfm.records import Interface, Target, WindowPlane
from ari_sfm.simulate.particles import render_particle_image
from ari_sfm.simulate.render import add_discs

FRAME = "f000"


def cavity_body() -> Target:
    """Build test_cavity's body (``target_on_a_side.txt``).

    Ids 1.. in x-major order; rows y = -25, -15, 0, 15, 25 mm at z = 8, 0, -8, 0, 8 mm; x from -40
    (rows at z = 0: -35) to 30 mm in steps of 5 mm.

    Returns:
        A ``points3d`` target of the 73 body points (mm).
    """
    rows = ((-25.0, 8.0, -40.0), (-15.0, 0.0, -35.0), (0.0, -8.0, -40.0), (15.0, 0.0, -35.0), (25.0, 8.0, -40.0))
    points = [(x, y, z) for x in np.arange(-40.0, 30.1, 5.0) for y, z, first in rows if x >= first]
    return Target(type="points3d", points={k + 1: (float(x), float(y), float(z)) for k, (x, y, z) in enumerate(points)})


@dataclass(frozen=True)
class BodyView:
    """One camera's view of the body: intrinsics ``K``, ``cam_from_body``, ``image_size`` (w, h) and the
    window (``interface.plane`` in the body's frame, frame FRAME)."""

    K: np.ndarray
    cam_from_body: Pose
    image_size: tuple[int, int]
    interface: Interface

    def model(self) -> ExactModel:
        plane = self.interface.plane
        if plane is None:
            raise ValueError("the body's window has no plane")
        normal = self.cam_from_body.R @ plane.normal
        h = float(normal @ self.cam_from_body.apply(plane.point_mm))
        return ExactModel(PinholeModel(self.K), normal, self.interface.thickness_mm, self.interface.index,
                          self.interface.medium_index, distance_mm=h)

    def project(self, xyz: np.ndarray) -> np.ndarray:
        """Exact pixels (N, 2) of body points (N, 3)."""
        return self.model().project(self.cam_from_body.apply(np.asarray(xyz, float)))


def cavity_view(centre_mm: tuple[float, float, float] = (78.0, 16.0, -571.0), focal_px: float = 70.0 / 0.012,
                image_size: tuple[int, int] = (1280, 1024), roll_deg: float = 1.0) -> BodyView:
    """Place a camera looking at the body as test_cavity's first camera does.

    The camera is aimed at the body's origin, image y along the body's -y, behind a 6 mm acrylic wall
    whose water-side face is z = -125 mm (water behind).

    Args:
        centre_mm: the camera centre in the body frame (mm).
        focal_px: the focal length (px).
        image_size: the image size (w, h) in px.
        roll_deg: the roll of the image about the optical axis (degrees).

    Returns:
        The camera's view of the body.
    """
    centre = np.asarray(centre_mm, float)
    z = -centre / np.linalg.norm(centre)
    up = np.array([0.0, 1.0, 0.0])
    y = -(up - (up @ z) * z)
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    a = math.radians(roll_deg)
    x, y = math.cos(a) * x + math.sin(a) * y, -math.sin(a) * x + math.cos(a) * y
    R = np.stack([x, y, z])
    K = np.array([[focal_px, 0, (image_size[0] - 1) / 2 + 7.0], [0, focal_px, (image_size[1] - 1) / 2 - 5.0],
                  [0, 0, 1.0]])
    plane = WindowPlane(FRAME, np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -131.0]))
    interface = Interface(thickness_mm=6.0, index=1.49, medium_index=1.333, plane=plane)
    return BodyView(K, Pose(R, -R @ centre), (int(image_size[0]), int(image_size[1])), interface)


@dataclass(frozen=True)
class Distractors:
    """What else the image shows."""

    particles: int = 400  # specks of 1.5-3 px in the water
    dot_like: int = 6  # stray blobs of a dot's size, far from every body dot (bubbles, large particles)
    streak: bool = True  # a wall's bright horizontal streak between two rows of dots, and a bright vertical edge
    glare: bool = True  # a broad soft glare over part of the body (an uneven background)
    reflection: bool = True  # a faint copy of one row of dots, half a spacing along, a quarter across
    beside: tuple[int, ...] = ()  # body ids with a stray dot of their size right beside them
    beside_diameters: float = 1.35  # its centre this many diameters from the body dot's (a gap of 0.35 diameters)


@dataclass(frozen=True)
class BodyImage:
    """A rendered image and its truth: every body point's exact pixel (``ids``, ``pixels``), which of them are
    wholly inside the image (``visible``), and each dot's diameter (px)."""

    image: np.ndarray
    ids: np.ndarray
    pixels: np.ndarray
    visible: np.ndarray
    diameters_px: np.ndarray


def render_body_image(view: BodyView, target: Target, diameter_mm: float = 1.0,
                      distractors: Distractors = Distractors(), seed: int = 0, bit_depth: int = 8,
                      peak: float = 200.0, noise_sigma: float = 2.0) -> BodyImage:
    """Render the body's dots seen by a view, with distractors and noise.

    The background rises from 15 to 55 grey levels left to right (8-bit scale).

    Args:
        view: the camera's view of the body.
        target: the body (its 3D points, mm).
        diameter_mm: each dot's diameter (mm).
        distractors: what else the image shows.
        seed: the random seed.
        bit_depth: 8 (uint8) or 16 (uint16 holding 12 bits: every level x 16).
        peak: each dot's brightness (grey levels, 8-bit scale).
        noise_sigma: the standard deviation of the Gaussian noise (grey levels, 8-bit scale).

    Returns:
        The image and its truth.

    Raises:
        ValueError: if ``bit_depth`` is not 8 or 16.
    """
    rng = np.random.default_rng(seed)
    ids, xyz = target.points_3d()
    uv = view.project(xyz)
    half = 0.5 * diameter_mm
    scale_x = np.linalg.norm(view.project(xyz + [half, 0, 0]) - view.project(xyz - [half, 0, 0]), axis=1)
    scale_y = np.linalg.norm(view.project(xyz + [0, half, 0]) - view.project(xyz - [0, half, 0]), axis=1)
    diameters = 0.5 * (scale_x + scale_y)
    w, h = view.image_size
    visible = np.isfinite(uv).all(axis=1) & (uv[:, 0] > diameters) & (uv[:, 0] < w - 1 - diameters) & (
        uv[:, 1] > diameters) & (uv[:, 1] < h - 1 - diameters)
    spacing = float(np.median(np.sort(np.linalg.norm(uv[:, None] - uv[None], axis=2), axis=1)[:, 1]))
    d_mean = float(np.mean(diameters[visible]))
    image = np.tile(15.0 + 40.0 * np.arange(w) / (w - 1), (h, 1))
    if distractors.glare:
        gu, gv = uv[visible].mean(axis=0) + [0.25 * spacing * 3, -0.5 * spacing]
        vv, uu = np.mgrid[0:h, 0:w]
        image += 70.0 * np.exp(-((uu - gu) ** 2 + (vv - gv) ** 2) / (2 * (1.5 * spacing) ** 2))
    if distractors.streak:
        rows_v = np.sort(uv[visible, 1])
        gaps = np.diff(rows_v)
        k = int(np.argmax(gaps))
        v_line = 0.5 * (rows_v[k] + rows_v[k + 1])
        vv = np.arange(h)[:, None]
        image += 150.0 * np.exp(-((vv - v_line - 0.01 * np.arange(w)[None, :]) ** 2) / 2.0)  # slightly tilted
        u_edge = max(0.5 * uv[visible, 0].min(), 3 * d_mean)
        image += 90.0 * np.exp(-((np.arange(w)[None, :] - u_edge) ** 2) / (2 * 3.0 ** 2))
    image = add_discs(image, uv[visible], diameters[visible], peak)
    if distractors.reflection:
        row = np.abs(xyz[:, 1] - xyz[np.argmax(xyz[:, 1]), 1]) < 1e-9
        sel = visible & row
        image = add_discs(image, uv[sel] + [0.5 * spacing, 0.25 * spacing], diameters[sel], 0.45 * peak)
    stray = []
    for pid in distractors.beside:
        k = int(np.nonzero(ids == pid)[0][0])
        a = rng.uniform(0, 2 * math.pi)
        stray.append(uv[k] + distractors.beside_diameters * diameters[k] * np.array([math.cos(a), math.sin(a)]))
    for _ in range(distractors.dot_like):
        for _ in range(1000):
            p = rng.uniform([3 * d_mean, 3 * d_mean], [w - 3 * d_mean, h - 3 * d_mean])
            if np.min(np.linalg.norm(uv[visible] - p, axis=1)) > 1.5 * spacing:
                stray.append(p)
                break
    if stray:
        image = add_discs(image, np.array(stray), d_mean, peak)
    if distractors.particles:
        specks = rng.uniform([0, 0], [w, h], size=(distractors.particles, 2))
        image += render_particle_image(specks, (w, h), float(rng.uniform(1.5, 3.0)),
                                       peak=rng.uniform(40, 200, distractors.particles), background=0.0,
                                       noise_sigma=0.0).astype(float)
    image += rng.normal(0.0, noise_sigma, image.shape)
    if bit_depth == 8:
        out = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    elif bit_depth == 16:
        out = np.clip(np.rint(image * 16.0), 0, 4095).astype(np.uint16)
    else:
        raise ValueError(f"bit_depth must be 8 or 16 (got {bit_depth})")
    return BodyImage(out, ids, uv, visible, diameters)
