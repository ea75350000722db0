"""The floor's compiled normalised DLT (ari_sfm.calibration.floor_fit.projective_maps) against known homographies and
cameras, OpenCV's and LAPACK's least eigenvector."""
from __future__ import annotations

import cv2
import numpy as np

from ari_sfm.calibration.floor_fit import projective_maps


def homographies(xy, uv):
    return projective_maps(np.ascontiguousarray(xy, dtype=float), np.ascontiguousarray(uv, dtype=float))


def _views(rng: np.random.Generator, sizes: list[int]) -> tuple[list, list, list]:
    xy, uv, truth = [], [], []
    for n in sizes:
        H = np.array([[900.0, 40.0, 1200.0], [-30.0, 950.0, 1000.0], [0.0, 0.0, 1.0]])
        H[2, :2] = rng.uniform(-2e-3, 2e-3, 2)
        H[:2, :2] += rng.normal(0, 50, (2, 2))
        p = rng.uniform(-60, 60, (n, 2))
        q = np.c_[p, np.ones(n)] @ H.T
        xy.append(p), uv.append(q[:, :2] / q[:, 2:]), truth.append(H)
    return xy, uv, truth


def test_noise_free_views_give_their_homographies_also_from_four_points():
    for n in (88, 30, 4):  # 4 points: 8 equations, the homography is their null vector
        xy, uv, truth = _views(np.random.default_rng(n), [n] * 3)
        H = homographies(np.array(xy), np.array(uv))
        for h, t in zip(H, truth):
            assert np.allclose(h / h[2, 2], t, rtol=1e-8, atol=1e-8)


def test_noisy_views_agree_with_opencv_and_non_finite_points_give_nan():
    rng = np.random.default_rng(1)
    xy, uv, _ = _views(rng, [88, 88, 88])
    uv = np.array([q + rng.normal(0, 0.5, q.shape) for q in uv])
    H = homographies(np.array(xy), uv)
    for h, p, q in zip(H, xy, uv):
        ref = cv2.findHomography(p, q, 0)[0]  # the same DLT, then refined: within the noise's effect
        grid = np.c_[np.mgrid[-60:61:20, -60:61:20].reshape(2, -1).T, np.ones(49)]
        a, b = grid @ (h / h[2, 2]).T, grid @ ref.T
        assert np.abs(a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:]).max() < 0.5
    uv[0, 3, 0] = np.nan
    assert not np.isfinite(homographies(np.array(xy), uv)).all()


def test_inverse_iteration_converges_to_the_least_eigenvector_even_at_ten_pixels_of_noise():
    rng = np.random.default_rng(2)
    for sigma in (0.0, 0.5, 10.0):
        xy, uv, _ = _views(rng, [12, 88, 200])
        for p, q in zip(xy, uv):
            q = q + rng.normal(0, sigma, q.shape)
            h = homographies(p[None], q[None])[0]

            def normalised(x):
                c = x.mean(axis=0)
                s = np.sqrt(2.0) / np.sqrt(np.mean(np.sum((x - c) ** 2, axis=1)))
                return (x - c) * s, np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1.0]])

            (a, Ta), (b, Tb) = normalised(p), normalised(q)
            ax, ay, bx, by = a[:, 0], a[:, 1], b[:, 0], b[:, 1]
            one, zero = np.ones_like(ax), np.zeros_like(ax)
            rows = np.r_[np.c_[ax, ay, one, zero, zero, zero, -bx * ax, -bx * ay, -bx],
                         np.c_[zero, zero, zero, ax, ay, one, -by * ax, -by * ay, -by]]
            least = np.linalg.eigh(rows.T @ rows)[1][:, 0]
            ours = (Tb @ h @ np.linalg.inv(Ta)).ravel()  # back to the normalised frame
            ours /= np.linalg.norm(ours)
            assert min(np.abs(ours - least).max(), np.abs(ours + least).max()) < 1e-10


def test_noise_free_bodies_give_their_cameras_and_noisy_ones_the_least_eigenvector():
    """3D points: the 3 x 4 camera of the normalised DLT (11 dof), exact from 6 points without noise; with
    noise the least eigenvector of the normalised 12 x 12 system, as LAPACK finds it."""
    rng = np.random.default_rng(3)
    K = np.array([[3400.0, 0.0, 640.0], [0.0, 3400.0, 512.0], [0.0, 0.0, 1.0]])
    for n, sigma in ((6, 0.0), (50, 0.0), (300, 0.0), (300, 0.3)):
        R = np.linalg.qr(rng.normal(size=(3, 3)))[0] * np.array([1.0, 1.0, 1.0])
        R *= np.sign(np.linalg.det(R))
        P = K @ np.c_[R, [5.0, -3.0, 600.0]]
        X = rng.uniform(-60, 60, (n, 3))
        q = np.c_[X, np.ones(n)] @ P.T
        uv = q[:, :2] / q[:, 2:] + rng.normal(0, sigma, (n, 2))
        ours = homographies(X[None], uv[None])[0]
        if sigma == 0.0:
            assert np.allclose(ours / ours[2, 3], P / P[2, 3], rtol=1e-7, atol=1e-7)
            continue
        c, s3 = X.mean(axis=0), np.sqrt(3.0) / np.sqrt(np.mean(np.sum((X - X.mean(axis=0)) ** 2, axis=1)))
        cb, s2 = uv.mean(axis=0), np.sqrt(2.0) / np.sqrt(np.mean(np.sum((uv - uv.mean(axis=0)) ** 2, axis=1)))
        a, b = (X - c) * s3, (uv - cb) * s2
        A4, zero = np.c_[a, np.ones(n)], np.zeros((n, 4))
        rows = np.r_[np.c_[A4, zero, -b[:, :1] * A4], np.c_[zero, A4, -b[:, 1:] * A4]]
        least = np.linalg.eigh(rows.T @ rows)[1][:, 0]
        Ta = np.r_[np.c_[s3 * np.eye(3), -s3 * c], [[0.0, 0.0, 0.0, 1.0]]]
        Tb = np.array([[s2, 0.0, -s2 * cb[0]], [0.0, s2, -s2 * cb[1]], [0.0, 0.0, 1.0]])
        back = (Tb @ ours @ np.linalg.inv(Ta)).ravel()
        back /= np.linalg.norm(back)
        assert min(np.abs(back - least).max(), np.abs(back + least).max()) < 1e-10
