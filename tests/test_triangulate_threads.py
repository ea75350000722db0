"""The exact model's triangulation kernel run in slices of points on threads (ari_sfm/reconstruction/triangulate.py)."""
from __future__ import annotations

import numpy as np

from ari_sfm.io import parse_calibration
from ari_sfm.reconstruction import triangulate as T
from ari_sfm.simulate import make_scene


def test_triangulation_in_slices_on_threads_is_the_one_call(monkeypatch):
    """Points triangulated in slices handed out to threads are those of one kernel call over all of
    them, bit for bit (each point is independent: the slices' bounds lose and repeat none)."""
    cal = parse_calibration(make_scene("arc4", seed=0, sigma_px=0.0).truth)
    rng = np.random.default_rng(5)
    centres = np.array([p.t for p in cal.frames.values()])
    X_true = rng.uniform(centres.min(axis=0) - 20, centres.max(axis=0) + 20, (997, 3))
    tracks = {c: cal.project_world(c, X_true) + rng.normal(0, 0.3, (len(X_true), 2)) for c in cal.cameras}
    tracks[next(iter(cal.cameras))][::7] = np.nan
    one = T.triangulate_pixels(cal, tracks)
    monkeypatch.setattr(T, "_cores", lambda: 3)
    monkeypatch.setattr(T, "PARALLEL_MIN_POINTS", 100)
    monkeypatch.setattr(T, "PARALLEL_CHUNK_POINTS", 37)
    sliced = T.triangulate_pixels(cal, tracks)
    assert np.isfinite(one[0]).all(axis=1).sum() > 900
    assert np.linalg.norm(one[0] - X_true, axis=1)[np.isfinite(one[0][:, 0])].max() < 1.0  # points, not noise
    for a, b in zip(one, sliced):
        assert np.array_equal(a, b, equal_nan=True)
