"""The COLMAP plugin's way back: refine a COLMAP reconstruction made behind a flat window.

``problem`` (variables, residuals, Jacobians through the exact model), ``schur`` (points
eliminated, a small LM loop), ``refine`` (start, distance search, outputs), ``window`` (WINDOW.yaml).
"""
from .refine import RefineResult, refine_colmap, write_refined

__all__ = ["RefineResult", "refine_colmap", "write_refined"]
