"""The argument types with which ari-sfm calls each compiled kernel from Python: what
:mod:`ari_sfm.kernel_build` compiles into the wheel (a kernel called only from other kernels is compiled
with its caller). Written by ``scripts/record_kernel_signatures.py`` from the commands a user runs; a
call with other types still works (numba compiles it on its first use).
"""
from __future__ import annotations

from typing import Literal

from numba.core.types import Array, boolean, float32, float64, int64


def array(dtype, ndim: int, layout: Literal["C", "F", "A"] = "C", readonly: bool = False) -> Array:
    """An array type of numba.

    Args:
        dtype: the element type (e.g. ``float64``).
        ndim: the number of dimensions.
        layout: "C" contiguous, "F" Fortran-contiguous, "A" any strides.
        readonly: a read-only array.

    Returns:
        numba's ``Array`` type.
    """
    return Array(dtype, ndim, layout, readonly=readonly)


SIGNATURES = {
    'ari_sfm.colmap.refine.chain_kernels': {
        'chain_observations': [
            (array(float64, 3), array(float64, 3), array(float64, 2), array(float64, 2), array(float64, 3),
             array(float64, 2), array(float64, 3), array(float64, 2), boolean, array(float64, 2),
             array(float64, 3), array(float64, 2), array(float64, 3), int64, int64, int64, array(float64, 3)),
        ],
    },
    'ari_sfm.factors.robust': {
        '_irls_batch': [
            (array(float64, 1), float64),
        ],
        'weighted_residuals': [
            (array(float64, 2), array(float64, 2), float64, array(float64, 1), boolean, float64),
        ],
    },
    'ari_sfm.solver.schur_kernels': {
        'assemble_entries': [
            (array(float64, 2), array(float64, 3), array(int64, 2), array(float64, 3), array(int64, 1),
             array(float64, 1), int64, int64),
            (array(float64, 2), array(float64, 3), array(int64, 2), array(float64, 3), array(int64, 1, 'A'),
             array(float64, 1), int64, int64),
        ],
        'fill_y': [
            (array(float64, 3), array(int64, 1), array(int64, 1), array(int64, 2), array(int64, 1),
             array(float64, 3), array(int64, 1), int64, int64, int64, array(float64, 2)),
            (array(float64, 3), array(int64, 1, 'A'), array(int64, 1), array(int64, 2), array(int64, 1),
             array(float64, 3), array(int64, 1), int64, int64, int64, array(float64, 2)),
        ],
    },
    'ari_sfm.factors.view_kernels': {
        'accumulate_views': [
            (array(float64, 3), array(float64, 3), array(float64, 2), array(float64, 3), array(float64, 2),
             array(float64, 2), array(float64, 3), array(int64, 1), array(float64, 1), array(float64, 1),
             array(float64, 2), array(float64, 1), boolean, boolean, array(float64, 1), array(float64, 2),
             array(float64, 3), array(float64, 2), array(float64, 3), array(float64, 2), array(float64, 1),
             array(boolean, 1)),
        ],
        'add_camera': [
            (array(float64, 3), array(float64, 2), array(float64, 3), array(float64, 2), array(float64, 1),
             array(int64, 1), array(int64, 1), array(float64, 3), array(float64, 2), array(float64, 3),
             array(float64, 2), array(float64, 1)),
        ],
        'chain_rows': [
            (array(float64, 3), array(float64, 3), array(float64, 2), array(float64, 2), array(float64, 2),
             array(float64, 3), array(int64, 1), array(float64, 1), array(float64, 1), array(float64, 2),
             array(float64, 1), boolean, boolean, int64, array(float64, 3)),
        ],
        'rig_transforms': [
            (array(float64, 3), array(float64, 2), array(float64, 3), array(float64, 2), array(int64, 1),
             array(int64, 1), array(float64, 1), float64, boolean),
        ],
        'transform_points': [
            (array(float64, 2), array(float64, 3), array(float64, 2), array(int64, 1)),
        ],
    },
    'ari_sfm.calibration.floor_fit': {
        'warp_residuals': [
            (array(float64, 3), array(float64, 3), int64, boolean),
        ],
    },
    'ari_sfm.models.kernels': {
        'ari_batch': [
            (array(float64, 2), array(float64, 1), array(float64, 1), array(float64, 2), array(float64, 1),
             float64, float64, float64, int64, boolean),
            (array(float64, 2), array(float64, 1), array(float64, 1), array(float64, 2),
             array(float64, 1, readonly=True), float64, float64, float64, int64, boolean),
        ],
        'distort_batch': [
            (array(float64, 2), array(float64, 1)),
        ],
        'exact_batch': [
            (array(float64, 2), array(float64, 1), array(float64, 1), array(float64, 2), float64,
             array(float64, 1), float64, float64, int64, boolean),
        ],
        'exact_rays_batch': [
            (array(float64, 2), array(float64, 1), array(float64, 1), float64, float64, float64, float64),
        ],
        'incidence_batch': [
            (array(float64, 2), array(float64, 1), float64, array(float64, 1), float64, float64, int64),
        ],
        'pinhole_batch': [
            (array(float64, 2), array(float64, 1), int64, boolean),
        ],
        'solve_w_batch': [
            (array(float64, 1), array(float64, 1), float64, array(float64, 1), float64, float64, int64),
        ],
        'triangulate_exact': [
            (array(float64, 3), array(float64, 3), array(float64, 2), array(float64, 2), array(float64, 2),
             array(float64, 2), boolean, int64, float64, float64, float64, array(float64, 2),
             array(float64, 1), array(float64, 1), array(boolean, 1), array(int64, 1)),
        ],
        'undistort_batch': [
            (array(float64, 2), array(float64, 1), float64, float64),
        ],
    },
    'ari_sfm.particles.detect_kernels': {
        'block_statistics': [
            (array(float32, 2), array(float32, 2), array(int64, 1), array(int64, 1), int64, int64, int64,
             float64, float64, float64, float64, float64),
        ],
        'connected_regions': [
            (array(float32, 2), array(float32, 2), float64, float64, array(int64, 1), array(int64, 1), int64),
        ],
        'fit_round': [
            (array(float32, 2), array(float64, 2), array(int64, 1), array(int64, 1), array(int64, 1),
             array(int64, 1), array(float64, 1), array(float64, 1), array(float64, 1), array(float64, 1),
             array(float64, 1), array(boolean, 1), array(boolean, 1), float64, float64, float64, int64,
             float64, float64),
        ],
        'level_and_noise': [
            (array(float32, 2), array(float32, 2), array(float32, 2), array(float64, 1), array(float64, 1),
             float64, float64, float64),
        ],
        'levenberg_marquardt': [
            (int64, array(float64, 2), array(float64, 2), array(float64, 2), array(float64, 2), int64,
             float64),
        ],
        'local_maxima': [
            (array(float32, 2), array(float32, 2), float64, float64),
        ],
        'on_ridge': [
            (array(float32, 2), array(float64, 1), array(float64, 1), array(float64, 1), array(float64, 1),
             array(float64, 2), int64, float64, float64, float64),
        ],
        'own_pixels': [
            (array(float32, 2), array(float64, 2), array(int64, 1), array(int64, 1), array(float64, 1),
             array(float64, 1), array(float64, 1), array(float64, 1), array(float64, 1), array(int64, 1),
             array(int64, 1)),
        ],
        'render': [
            (array(float64, 2), array(int64, 1), array(int64, 1), array(float64, 1), array(float64, 1),
             array(float64, 1), array(float64, 1), array(float64, 1), int64),
        ],
        'shape_hessians': [
            (array(float64, 2), array(float64, 1), float64),
        ],
        'without_hot_pixels': [
            (array(float32, 2), array(float32, 2), float64),
        ],
    },
    'ari_sfm.particles.disparity_kernels': {
        'joint_counts': [
            (array(float64, 3), float64),
        ],
    },
    'ari_sfm.particles.match_kernels': {
        'band_pairs': [
            (array(float64, 3), array(float64, 2), float64, float64),
        ],
        'greedy_rows': [
            (array(int64, 2), array(int64, 1), array(boolean, 1), array(int64, 1)),
        ],
        'join_within_reach': [
            (array(int64, 2), array(int64, 1), array(int64, 1), array(int64, 1), int64, boolean, int64,
             boolean, array(float64, 2), array(float64, 2), array(int64, 1), array(float64, 1), float64),
        ],
        'score_combos': [
            (array(int64, 2), array(float64, 2), array(float64, 2), array(int64, 1), array(float64, 1),
             array(float64, 2), array(float64, 1), array(float64, 1), array(float64, 1), float64, float64,
             float64),
        ],
    },
    'ari_sfm.se3_kernel': {
        'retract_poses_kernel': [
            (array(float64, 3), array(float64, 2), array(float64, 2)),
        ],
        'se3_exp_kernel': [
            (array(float64, 2),),
        ],
    },
}
