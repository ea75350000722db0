"""The COLMAP plugin's way back: refine a COLMAP reconstruction made behind a flat window.

``options`` (:class:`RefineColmapOptions`, the modes ``Mount``, ``Approximation``, ``Backend``), ``inputs``
(the model read and checked, its scale), ``paraxial`` (the start state: COLMAP's cameras as paraxial virtual
cameras), ``start`` (the distance search, a long chain's start through ``chain_start``), ``plan`` (the stages:
:func:`~.plan.plan_refinement`, :func:`~.plan.run_stage`), ``outputs`` (the calibration, the COLMAP
approximation, the report), ``refine`` (:func:`refine_colmap`: runs them; :func:`write_refined`);
``problem`` (variables, residuals, Jacobians through the exact model), ``solver``, ``window`` (WINDOW.yaml),
``settings`` (the defaults). The entry points load on first use, so that reading ``settings``, ``options`` or
``window`` does not load pycolmap.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .options import Approximation, Backend, Mount, RefineColmapOptions
    from .plan import RefineStage, plan_refinement, run_stage
    from .refine import RefineResult, refine_colmap, write_refined

__all__ = ["Approximation", "Backend", "Mount", "RefineColmapOptions", "RefineResult", "RefineStage",
           "plan_refinement", "refine_colmap", "run_stage", "write_refined"]
_HOMES = {"Approximation": "options", "Backend": "options", "Mount": "options", "RefineColmapOptions": "options",
          "RefineStage": "plan", "plan_refinement": "plan", "run_stage": "plan", "RefineResult": "refine",
          "refine_colmap": "refine", "write_refined": "refine"}


def __getattr__(name: str):
    """The public names, each imported from its module on first use."""
    if name in _HOMES:
        from importlib import import_module

        return getattr(import_module(f"{__name__}.{_HOMES[name]}"), name)
    raise AttributeError(f"module 'ari_sfm.colmap.refine' has no attribute {name!r}")
