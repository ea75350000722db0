"""The pf projection: Paolillo et al.'s 3x3x3 world-to-pixel polynomial per camera (paper Eq. 14), and
its camera-frame adapter. Its fit is the baseline's (:mod:`ari_sfm.baselines.polynomial`); calibration.json
loading needs only this (a camera's ``pf`` key)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..geometry import Pose

DEGREE = 3
# Eq. 14's order: k outermost, then j, then i.
EXPONENTS: tuple[tuple[int, int, int], ...] = tuple(
    (i, j, k) for k in range(DEGREE + 1) for j in range(DEGREE + 1 - k) for i in range(DEGREE + 1 - k - j))
NUM_TERMS = len(EXPONENTS)  # 20


def design_matrix(Xn: np.ndarray) -> np.ndarray:
    """Monomials (N, 20) of normalised points (N, 3), columns in :data:`EXPONENTS` order."""
    Xn = np.asarray(Xn, float).reshape(-1, 3)
    powers = [np.ones((len(Xn), 3))]
    for _ in range(DEGREE):
        powers.append(powers[-1] * Xn)
    return np.stack([powers[i][:, 0] * powers[j][:, 1] * powers[k][:, 2] for i, j, k in EXPONENTS], axis=1)


@dataclass(frozen=True)
class PolynomialMap:
    """One camera's world-to-pixel polynomial (40 coefficients) and its normalisation."""

    mean: np.ndarray  # (3,) mm
    scale: np.ndarray  # (3,) mm
    coef_u: np.ndarray  # (20,)
    coef_v: np.ndarray  # (20,)
    rank: int = NUM_TERMS  # rank of the design matrix at the fit (20: well posed)

    def project_world(self, X_world: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of world points (N, 3)."""
        A = design_matrix((np.asarray(X_world, float).reshape(-1, 3) - self.mean) / self.scale)
        return np.stack([A @ self.coef_u, A @ self.coef_v], axis=1)

    def to_json(self, world: str = "ari") -> dict[str, Any]:
        return {"world": world, "exponents": [list(e) for e in EXPONENTS], "mean": self.mean.tolist(),
                "scale": self.scale.tolist(), "coef_u": self.coef_u.tolist(), "coef_v": self.coef_v.tolist(),
                "rank": int(self.rank)}

    @staticmethod
    def from_json(d: dict[str, Any]) -> PolynomialMap:
        """Parse the camera's ``pf`` entry (ValueError on a malformed one)."""
        if [tuple(e) for e in d.get("exponents", EXPONENTS)] != list(EXPONENTS):
            raise ValueError("pf.exponents must be the 20 monomials of Eq. 14 in their order")
        arrays = {}
        for key, n in (("mean", 3), ("scale", 3), ("coef_u", NUM_TERMS), ("coef_v", NUM_TERMS)):
            a = np.asarray(d[key], float)
            if a.shape != (n,) or not np.all(np.isfinite(a)):
                raise ValueError(f"pf.{key} must be {n} finite numbers")
            arrays[key] = a
        if np.any(arrays["scale"] <= 0):
            raise ValueError("pf.scale must be > 0")
        return PolynomialMap(arrays["mean"], arrays["scale"], arrays["coef_u"], arrays["coef_v"],
                             int(d.get("rank", NUM_TERMS)))


class PolynomialModel:
    """A camera-frame adapter: ``project(X_cam)`` maps to the world and evaluates the polynomial.

    Lets the project's evaluation code (which projects camera-frame points)
    use a PF camera. PF has no rays: :meth:`backproject` raises.
    """

    def __init__(self, poly: PolynomialMap, world_from_cam: Pose) -> None:
        self.poly = poly
        self.world_from_cam = world_from_cam

    def project(self, X_cam: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of camera-frame points (N, 3)."""
        return self.poly.project_world(self.world_from_cam.apply(np.asarray(X_cam, float).reshape(-1, 3)))

    def backproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise ValueError("model pf maps world points to pixels only: a polynomial has no rays to back-project")
