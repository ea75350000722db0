"""The reconstructed points as records: :class:`FramePoints` per frame and :class:`Points`, which
reads and writes ``points.json`` (DATASET_FORMAT.md). Made by :mod:`ari_sfm.reconstruction.reconstruct`,
measured by :mod:`ari_sfm.reconstruction.metrics` and :mod:`ari_sfm.reconstruction.reference` (which
therefore need not import the reconstruction)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class FramePoints:
    """The triangulated corners of one reconstruction frame (world frame of the calibration, mm)."""

    stage_mm: float | None
    ids: np.ndarray  # (N,) int target corner ids
    xyz: np.ndarray  # (N, 3) world points
    ray_gap_mm: np.ndarray  # (N,) how far the viewing rays missed each other (triangulate.py)
    reprojection_rmse_px: float | None = None  # over the frame's corners and cameras; None when loaded
    num_cameras: np.ndarray | None = None  # (N,) cameras that saw each corner; None when loaded

    def __len__(self) -> int:
        return len(self.ids)


@dataclass(frozen=True)
class Points:
    """Reconstructed frames ``{name: FramePoints}`` (in the order of the dataset)."""

    frames: dict[str, FramePoints] = field(default_factory=dict)
    calibration: str | None = None  # the calibration file named in points.json, when loaded

    @property
    def num_points(self) -> int:
        return sum(len(f) for f in self.frames.values())

    def save(self, path: str | Path, calibration_name: str, provenance: dict | None = None) -> None:
        """Write ``points.json`` atomically (validated first; a bad frame writes nothing).

        Args:
            path: the file to write.
            calibration_name: the calibration file named in points.json.
            provenance: which calibration and dataset made the points (:mod:`ari_sfm.provenance`), or None.
        """
        from ..io import save_points

        save_points(path, {name: {"stage_mm": f.stage_mm, "ids": f.ids, "xyz": f.xyz, "ray_gap_mm": f.ray_gap_mm}
                           for name, f in self.frames.items()}, calibration_name, provenance)

    @staticmethod
    def load(path: str | Path) -> Points:
        """Read and validate ``points.json``."""
        from ..io import load_points

        data = load_points(path)
        frames = {name: FramePoints(f["stage_mm"], f["ids"], f["xyz"], f["ray_gap_mm"])
                  for name, f in data["frames"].items()}
        return Points(frames, data["calibration"])
