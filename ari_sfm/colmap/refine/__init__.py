"""The COLMAP plugin's way back: refine a COLMAP reconstruction made behind a flat window.

``problem`` (variables, residuals, Jacobians through the exact model), ``refine`` (start, distance
search, sliding blocks, outputs), ``window`` (WINDOW.yaml), ``settings`` (the defaults). The entry points
load on first use, so that reading ``settings`` or ``window`` does not load pycolmap.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .refine import RefineResult, refine_colmap, write_refined

__all__ = ["RefineResult", "refine_colmap", "write_refined"]


def __getattr__(name: str):
    if name in __all__:
        from . import refine

        return getattr(refine, name)
    raise AttributeError(f"module 'ari_sfm.colmap.refine' has no attribute {name!r}")
