"""The measured volume: an axis-aligned box in some frame (a camera's, or the world)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ari_sfm.geometry import Pose


@dataclass(frozen=True)
class Volume:
    """Box ``min_mm <= box_from_world(X) <= max_mm`` (mm).

    Infinite bounds are allowed (a depth range alone: only z bounded).
    """

    min_mm: np.ndarray  # (3,)
    max_mm: np.ndarray  # (3,)
    box_from_world: Pose = field(default_factory=Pose.identity)

    @staticmethod
    def depth_range(z_min_mm: float, z_max_mm: float, box_from_world: Pose | None = None) -> Volume:
        """The slab ``z_min <= z <= z_max`` of a frame.

        Args:
            z_min_mm: Near bound (mm).
            z_max_mm: Far bound (mm).
            box_from_world: The slab's frame; None for the world (camera 0's frame).

        Returns:
            The volume, unbounded in x and y.

        Raises:
            ValueError: ``z_max_mm`` is not greater than ``z_min_mm``.
        """
        if not z_max_mm > z_min_mm:
            raise ValueError(f"depth range must have max > min (got {z_min_mm}, {z_max_mm})")
        return Volume(np.array([-np.inf, -np.inf, z_min_mm]), np.array([np.inf, np.inf, z_max_mm]),
                      box_from_world or Pose.identity())

    @property
    def center_world(self) -> np.ndarray:
        """The box centre in the world (x, y of an unbounded box: 0)."""
        lo, hi = self.min_mm, self.max_mm
        bounded = np.isfinite(lo) & np.isfinite(hi)
        c = np.where(bounded, 0.5 * (np.where(bounded, lo, 0.0) + np.where(bounded, hi, 0.0)), 0.0)
        return self.box_from_world.inverse().apply(c)

    def contains(self, X_world: np.ndarray, margin_mm: float = 0.0) -> np.ndarray:
        """Which points lie inside the box.

        Args:
            X_world: Points (N, 3), world frame, mm.
            margin_mm: The box is grown by this on every side (mm).

        Returns:
            (N,) bool.
        """
        Xb = self.box_from_world.apply(np.asarray(X_world, float).reshape(-1, 3))
        return np.all((Xb >= self.min_mm - margin_mm) & (Xb <= self.max_mm + margin_mm), axis=1)

    def clip_rays(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where rays run inside the box (slab method).

        Args:
            origins: Ray origins (N, 3), world frame, mm.
            directions: Ray directions (N, 3), world frame.

        Returns:
            (s0, s1), each (N,): ``origin + s direction`` is inside the box for s0 <= s <= s1, s >= 0;
            NaN for rays that miss it.
        """
        o = self.box_from_world.apply(origins)
        d = np.asarray(directions, float) @ self.box_from_world.R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            a = (self.min_mm - o) / d
            b = (self.max_mm - o) / d
        lo = np.where(np.isnan(a), -np.inf, np.minimum(a, b))  # d = 0 and inside: no bound from that axis
        hi = np.where(np.isnan(b), np.inf, np.maximum(a, b))
        inside_flat = (d == 0) & (o >= self.min_mm) & (o <= self.max_mm)
        lo = np.where((d == 0) & inside_flat, -np.inf, lo)
        hi = np.where((d == 0) & inside_flat, np.inf, hi)
        lo = np.where((d == 0) & ~inside_flat, np.inf, lo)
        s0 = np.maximum(lo.max(axis=1), 0.0)
        s1 = hi.min(axis=1)
        miss = ~(s1 > s0) | ~np.isfinite(s1) | ~np.isfinite(s0)
        s0[miss] = np.nan
        s1[miss] = np.nan
        return s0, s1
