"""Corners whose residual stays beyond k sigma after convergence."""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from ..records import Observation


@dataclass(frozen=True)
class Outlier:
    camera: str
    set: str
    frame: str
    id: int
    residual_px: float
    added_mm: float | None = None

    def to_json(self) -> dict:
        out = {"camera": self.camera, "set": self.set, "frame": self.frame, "id": self.id,
               "residual_px": self.residual_px}
        if self.added_mm is not None:
            out["added_mm"] = self.added_mm
        return out

    @staticmethod
    def from_json(d: dict) -> Outlier:
        added = d.get("added_mm")
        return Outlier(str(d["camera"]), str(d["set"]), str(d["frame"]), int(d["id"]), float(d["residual_px"]),
                       None if added is None else float(added))


def robust_sigma_px(residuals: Iterable[np.ndarray]) -> float:
    """sigma per coordinate from the median absolute residual (1.4826 MAD)."""
    r = np.concatenate([np.asarray(x, float).reshape(-1) for x in residuals])
    return float(1.4826 * np.median(np.abs(r))) if r.size else float("nan")


def find_outliers(pairs: Sequence[tuple[Observation, np.ndarray]], k_sigma: float = 5.0) -> tuple[list[Outlier], float]:
    """Find the corners whose residual's pixel distance exceeds k_sigma * sigma.

    Args:
        pairs: (observation, residual (M, 2)) pairs.
        k_sigma: the threshold, in sigmas.

    Returns:
        The outlier corners, and sigma (px, robust, per coordinate; NaN without pairs).
    """
    if not pairs:
        return [], float("nan")
    r = np.concatenate([np.asarray(x, float).reshape(-1, 2) for _, x in pairs])
    sigma = robust_sigma_px([r])
    d = np.sqrt(np.einsum("ij,ij->i", r, r))
    start = np.cumsum([0] + [len(x) for _, x in pairs])
    beyond = np.flatnonzero(d > k_sigma * sigma)
    pair = np.searchsorted(start, beyond, side="right") - 1  # each corner's pair, by the pairs' offsets
    out = []
    for k, p in zip(beyond.tolist(), pair.tolist()):
        obs = pairs[p][0]
        out.append(Outlier(obs.camera, obs.set, obs.frame, int(obs.ids[k - start[p]]), float(d[k]), obs.added_mm))
    return out, sigma


def without(observations: Sequence[Observation], outliers: Sequence[Outlier]) -> tuple[Observation, ...]:
    """Remove the outlier corners from observations.

    Args:
        observations: the records.
        outliers: the corners to remove.

    Returns:
        The observations, in their order, without those corners.
    """
    from dataclasses import replace

    drop: dict[tuple, set[int]] = {}
    for o in outliers:
        drop.setdefault((o.camera, o.set, o.frame, o.added_mm), set()).add(o.id)
    result = []
    for obs in observations:
        ids = drop.get((obs.camera, obs.set, obs.frame, obs.added_mm))
        if ids:
            keep = np.array([int(i) not in ids for i in obs.ids])
            obs = replace(obs, ids=obs.ids[keep], pixels=obs.pixels[keep])
        result.append(obs)
    return tuple(result)
