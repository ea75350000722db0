"""The generic bundle-adjustment solver, apart from any problem: Levenberg-Marquardt over a problem's
normal equations (:mod:`.levenberg_marquardt`) and their Schur complement over many small independent
blocks (:mod:`.schur`, its accumulations compiled in :mod:`.schur_kernels`). The rig calibration
(:mod:`ari_sfm.factors.packed_problem`: target frames as the blocks) and the points problems of
refine-colmap and self-calibration (:mod:`ari_sfm.colmap.refine.solver`: 3D points as the blocks) solve
with it."""
