"""The declared window (WINDOW.yaml ``interface.plane``, DATASET_FORMAT 1.1) in refine-colmap.

Coordinates: mount ``camera``: each COLMAP camera's frame (its housing; every camera's housing is
the one declared); mount ``world``: the COLMAP model's world in mm (its units times ``units_mm``
or the scale bar's factor). There is no target frame: ``frame`` must be absent or name these.

The declared plane gives the window variables directly: normal = ``plane.normal``, distance
(mount camera: h, the face's distance from the camera centre; mount world: ``plane_mm``, the face
``normal . X = plane_mm``) = ``normal . point_mm``. A sigma of 0 holds that part (not estimated);
> 0 adds a prior residual per window, whitened by its sigma:

- normal: the chordal difference ``n - n_declared`` (3 rows, ~ radians);
- face position: ``d - n . point_mm`` (1 row, mm): how far the declared point is from the
  estimated face, along its normal (only while the distance is estimated).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ari_sfm.records import WindowPlane


@dataclass(frozen=True)
class WindowPrior:
    """Prior residuals on every window (W of them) from a declared plane; ``with_normal`` /
    ``with_distance``: which parts are priors (the others are held or not estimated)."""

    plane: WindowPlane
    with_normal: bool
    with_distance: bool

    @property
    def sigmas(self) -> np.ndarray:
        """Per-row sigmas of one window's prior (rad, mm)."""
        return np.array([np.radians(self.plane.sigma_deg)] * (3 if self.with_normal else 0)
                        + ([self.plane.sigma_mm] if self.with_distance else []))

    def errors(self, normal: np.ndarray, distance: float) -> np.ndarray:
        """Unwhitened errors of one window.

        Args:
            normal: its unit normal.
            distance: its distance.

        Returns:
            ``[n - n_declared (3, with_normal), d - n . point (with_distance)]``.
        """
        e = []
        if self.with_normal:
            e.append(normal - self.plane.normal)
        if self.with_distance:
            e.append([distance - normal @ self.plane.point_mm])
        return np.concatenate(e) if e else np.zeros(0)

    def jacobians(self) -> tuple[np.ndarray, np.ndarray]:
        """The errors' derivatives.

        Returns:
            d(errors)/d(normal) (rows, 3) in the ambient 3-vector (chain with a tangent basis) and
            d(errors)/d(distance) (rows,).
        """
        rows: list[np.ndarray] = []
        dd: list[np.ndarray] = []
        if self.with_normal:
            rows.append(np.eye(3))
            dd.append(np.zeros(3))
        if self.with_distance:
            rows.append(-self.plane.point_mm[None, :])
            dd.append(np.ones(1))
        return np.vstack(rows), np.concatenate(dd)

    def cost(self, normals: np.ndarray, distances: np.ndarray) -> float:
        """0.5 * sum of the squared whitened errors over every window.

        Args:
            normals: (W, 3) the windows' normals.
            distances: (W,) their distances.

        Returns:
            The cost.
        """
        s = self.sigmas
        return float(sum(0.5 * np.sum((self.errors(n, float(d)) / s) ** 2) for n, d in zip(normals, distances)))


def window_prior(plane: WindowPlane | None, estimate_distance: bool) -> WindowPrior | None:
    """The prior a declared plane adds.

    Args:
        plane: the declared plane, if any.
        estimate_distance: whether the distance is estimated (a distance prior needs it).

    Returns:
        The prior (None without a plane or when both parts are held).
    """
    if plane is None:
        return None
    with_normal = plane.sigma_deg > 0
    with_distance = plane.sigma_mm > 0 and estimate_distance
    return WindowPrior(plane, with_normal, with_distance) if (with_normal or with_distance) else None


def declared_window(plane: WindowPlane) -> tuple[np.ndarray, float]:
    """(unit normal, distance = normal . point_mm) of a declared plane in its frame."""
    n = np.asarray(plane.normal, float)
    n = n / np.linalg.norm(n)
    return n, float(n @ np.asarray(plane.point_mm, float))
