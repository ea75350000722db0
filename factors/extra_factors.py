"""The adapter that lets any gtsam factor join the numpy backend's normal equations.

A researcher's factors (priors on the normal, the intrinsics or a camera pose,
a between factor on two cameras, a factor on one target frame) are not
re-implemented: GTSAM linearises each one at every iteration
(``factor.linearize(values)``, whitened by its own noise model) and its
Jacobian blocks are added to the frame and global blocks of
:class:`~ari_sfm.solver.schur.NormalEquations`. Factors linking two target
frames would break the frames' block-diagonal structure: NotImplementedError
(``optimize_graph(backend="auto")`` then uses GTSAM).
"""
from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from ..solver.schur import NormalEquations
from .variables import PackedColumns, Variables


class ExtraFactors:
    """Factors a user added to a RigGraph: linearised by GTSAM, added to the packed normal equations.

    Supported: factors on global variables (K, C, N(w), H(w)) and at most one frame X(f).
    """

    def __init__(self, problem: PackedColumns, factors: Sequence[gtsam.NonlinearFactor]) -> None:
        self.problem = problem
        self.factors = list(factors)
        self.keys = sorted({k for f in self.factors for k in f.keys()})
        for f in self.factors:
            frames = {k for k in f.keys() if chr(gtsam.Symbol(k).chr()) == "x"}
            if len(frames) > 1:
                raise NotImplementedError("the numpy backend supports added factors on at most one target frame "
                                          f"(keys {[gtsam.DefaultKeyFormatter(k) for k in f.keys()]})")
            for k in f.keys():
                self._columns(k)  # validates the key

    def _columns(self, key: int) -> tuple[str, np.ndarray | int]:
        """('global', column indices) or ('frame', frame index) of a key."""
        p = self.problem
        ch, i = chr(gtsam.Symbol(key).chr()), gtsam.Symbol(key).index()
        if ch == "k" and i < len(p.camera_names):
            return "global", i * p.camera_block + np.arange(p.n_params)
        if ch == "c" and 0 < i < len(p.camera_names):
            return "global", i * p.camera_block + p.n_params + np.arange(6)
        if ch == "n" and i < len(p.normal_cols):
            return "global", p.normal_cols[i] + np.arange(2)
        if ch == "h" and p.estimate_distance and p.distance_cols is not None and i < len(p.distance_cols):
            return "global", np.array([p.distance_cols[i]])
        if ch == "x" and i < len(p.frame_names):
            return "frame", int(i)
        raise ValueError(f"added factor uses key {gtsam.DefaultKeyFormatter(key)}, not a variable of this problem")

    def _values(self, x: Variables) -> gtsam.Values:
        v = gtsam.Values()
        for key in self.keys:
            ch, i = chr(gtsam.Symbol(key).chr()), gtsam.Symbol(key).index()
            if ch == "k":
                v.insert(key, np.asarray(x.intrinsics[i], float))
            elif ch == "c":
                v.insert(key, gtsam.Pose3(gtsam.Rot3(x.world_R_cam[i]), x.world_t_cam[i]))
            elif ch == "x":
                v.insert(key, gtsam.Pose3(gtsam.Rot3(x.world_R_target[i]), x.world_t_target[i]))
            elif ch == "n":
                v.insert(key, x.normals[i])
            else:
                offset = x.distances[i]
                if offset is None:  # _columns admits a distance key only when it is estimated
                    raise ValueError(f"window {i}'s offset is not a variable")
                v.insert(key, np.array([float(offset)]))
        return v

    @property
    def linearized_error_is_error(self) -> bool:
        """A user factor's robust noise model makes the linearised error differ from the error."""
        return not self.factors

    def error(self, x: Variables) -> float:
        if not self.factors:
            return 0.0
        v = self._values(x)
        return float(sum(f.error(v) for f in self.factors))

    def add_to(self, sys: NormalEquations, x: Variables) -> None:
        if not self.factors:
            return
        v = self._values(x)
        for f in self.factors:
            lin = f.linearize(v)
            A, b = lin.jacobian()
            g_cols: list[tuple[np.ndarray, list[int]]] = []
            f_cols: list[int] = []
            frame: int | None = None
            col = 0
            for key in lin.keys():
                _, where = self._columns(key)
                if isinstance(where, int):  # a frame
                    frame, f_cols = where, list(range(col, col + 6))
                    col += 6
                else:
                    g_cols.append((where, list(range(col, col + len(where)))))
                    col += len(where)
            r = -np.asarray(b, float)
            gi = np.concatenate([w for w, _ in g_cols]) if g_cols else np.zeros(0, dtype=np.int64)
            Ag = A[:, [c for _, cs in g_cols for c in cs]] if g_cols else np.zeros((len(r), 0))
            sys.U[np.ix_(gi, gi)] += Ag.T @ Ag
            sys.g_global[gi] += Ag.T @ r
            if frame is not None:
                Af = A[:, f_cols]
                sys.V[frame] += Af.T @ Af
                sys.g_frame[frame] += Af.T @ r
                sys.W[frame][:, gi] += Af.T @ Ag
            sys.error += 0.5 * float(r @ r)

