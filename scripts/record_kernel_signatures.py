"""Write ari_sfm/kernel_signatures.py: the argument types with which ari-sfm's commands call its compiled
kernels, the list ari_sfm.kernel_build compiles into the wheel.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/record_kernel_signatures.py   # ~3 min once compiled

It runs the commands a user runs (run, compare, calibrate with each backend, evaluate, refine-colmap
in both mounts, the particle commands, the public projections) in this process on the bundled
datasets and small simulations, then lists every signature each kernel holds. Run it again when a
kernel or the types its callers pass change (tests/test_packaging.py checks that a calibration, a
triangulation and refine-colmap need nothing else).
"""
from __future__ import annotations

import os
import re
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "ari_sfm" / "kernel_signatures.py"

HEADER = '''"""The argument types with which ari-sfm calls each compiled kernel from Python: what
:mod:`ari_sfm.kernel_build` compiles into the wheel (a kernel called only from other kernels is compiled
with its caller). Written by ``scripts/record_kernel_signatures.py`` from the commands a user runs; a
call with other types still works (numba compiles it on its first use).
"""
from __future__ import annotations

from typing import Literal

from numba.core.types import Array, {types}


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
'''

SCALARS = {"float64": "float64", "float32": "float32", "int64": "int64", "int32": "int32", "uint8": "uint8",
           "uint16": "uint16", "bool": "boolean"}


def type_code(t) -> str:
    """Python source for a numba type (those ari-sfm's callers pass)."""
    from numba.core import types

    if isinstance(t, types.Array):
        if not t.aligned or str(t.dtype) not in SCALARS:
            raise ValueError(f"no source form for {t!r}")
        layout = "" if t.layout == "C" else f", {t.layout!r}"
        return f"array({SCALARS[str(t.dtype)]}, {t.ndim}{layout}{', readonly=True' if not t.mutable else ''})"
    if str(t) in SCALARS:
        return SCALARS[str(t)]
    raise ValueError(f"no source form for {t!r}")


def workloads(tmp: Path) -> None:
    """The commands, in this process."""
    import numpy as np
    from click.testing import CliRunner

    from ari_sfm.cli import main
    from ari_sfm.colmap import adapter
    from ari_sfm.colmap.refine import refine_colmap
    from ari_sfm.geometry import se3_exp
    from ari_sfm.models.exact import exact_project, incidence, solve_incidence
    from ari_sfm.models.pinhole import PinholeModel
    from ari_sfm.simulate.port_survey import port_survey, tank_rig

    def cli(*args) -> None:
        r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
        assert r.exit_code == 0, r.output
        print("  ari-sfm", *args[:2], file=sys.stderr)

    binocular, sample = ROOT / "datasets" / "binocular", ROOT / "datasets" / "sample"
    cli("run", binocular, "-o", tmp / "run")
    cli("compare", binocular, "-o", tmp / "compare")
    cli("calibrate", sample, "-o", tmp / "sample")
    cli("calibrate", sample, "-o", tmp / "sample_gtsam", "--backend", "gtsam")
    cli("evaluate", tmp / "sample" / "calibration.json", ROOT / "datasets" / "sample_truth_observations.json",
        "--solve-poses")
    for model in ("ari", "pinhole_dist"):
        cli("calibrate", binocular, "-o", tmp / model, "--model", model)
    cli("simulate", "tank_opposite", "-o", tmp / "tank")
    cli("calibrate", tmp / "tank" / "dataset", "-o", tmp / "tank_cal")
    cli("simulate", "particles", "-o", tmp / "ptv", "--particles", "300", "--frames", "3", "--render-frames", "1")
    ptv = tmp / "ptv"
    cli("calibrate", ptv / "calibration", "-o", tmp / "ptv_a", "--model", "exact")
    cli("particles", ptv / "experiment", "--calibration", tmp / "ptv_a" / "calibration.json",
        "-o", tmp / "ptv_p", "--workers", "0")
    cli("self-calibrate", ptv / "experiment", "--calibration", tmp / "ptv_a" / "calibration.json",
        "-o", tmp / "ptv_s", "--frames", "3", "--coarse-frames", "1")
    cli("detect-particles", ptv / "experiment", "-o", tmp / "ptv_d", "--workers", "0")  # in this process
    for truth, mount in ((port_survey(seed=0, num_images=8, num_points=300), "camera"),
                         (tank_rig(seed=0, num_frames=4, num_points=200), "world")):
        rec = adapter.reconstruction_from_arrays(
            [np.r_[p[:2] * 1.02, p[2:4]] for p in truth.params], truth.image_size, truth.sensor_from_rig,
            truth.rig_from_world, truth.image_camera, truth.image_frame, truth.xyz, truth.obs_image,
            truth.obs_point, truth.obs_uv)
        refine_colmap(adapter.bundle_adjust(rec), truth.interface, mount, max_iterations=5)
        print(f"  refine_colmap {mount}", file=sys.stderr)
    # the library's public functions beyond the commands' paths
    X = np.array([[1.0, 2.0, 400.0], [-20.0, 5.0, 420.0]])
    for dist in (np.zeros(5), np.array([0.1, -0.05, 1e-4, -1e-4, 0.01])):
        params = np.r_[3000.0, 3000.0, 1000.0, 800.0, dist]
        for jac in (False, True):
            exact_project(X, params, np.array([0.0, 0.0, 1.0]), 6.0, 1.5168, 1.333, 40.0, jacobians=jac)
        K = np.array([[3000.0, 0, 1000], [0, 3000, 800], [0, 0, 1]])
        PinholeModel(K, dist).distort_with_jacobians(X[:, :2] / 400)
    incidence(X, np.array([0.0, 0.0, 1.0]), 40.0, 6.0, 1.5168, 1.333)
    solve_incidence(np.array([1.0, 20.0]), np.array([300.0, 350.0]), 40.0, 6.0, 1.5168, 1.333)
    se3_exp(np.zeros((2, 6)))


def record_calls() -> dict:
    """Dispatcher -> the argument types of each of its calls from Python that needed a new specialisation
    (numba's ``_compile_for_args``: compiled or loaded from its cache; calls from kernels do not pass it)."""
    from numba.core import types
    from numba.core.dispatcher import Dispatcher, OmittedArg

    seen: dict = {}
    first_call = Dispatcher._compile_for_args

    def recording(self, *args, **kws):
        seen.setdefault(self, set()).add(tuple(types.Omitted(a.value) if isinstance(a, OmittedArg)
                                               else self.typeof_pyval(a) for a in args))
        return first_call(self, *args, **kws)

    Dispatcher._compile_for_args = recording
    return seen


def source_form(seen: dict) -> dict[str, dict[str, list[tuple[str, ...]]]]:
    """Module -> kernel -> its signatures (source form), of the ari_sfm kernels in ``seen``."""
    out: dict[str, dict[str, list[tuple[str, ...]]]] = {}
    for dispatcher, sigs in seen.items():
        module = dispatcher.py_func.__module__
        if module.startswith("ari_sfm."):
            out.setdefault(module, {})[dispatcher.py_func.__name__] = sorted(tuple(type_code(t) for t in sig)
                                                                            for sig in sigs)
    return {m: dict(sorted(k.items())) for m, k in sorted(out.items())}


def wrapped(sig: tuple[str, ...], width: int = 110) -> list[str]:
    """A signature as a tuple's source lines, broken between its types."""
    items = [f"{code}," for code in sig]
    items[-1] = items[-1] if len(sig) == 1 else items[-1][:-1]
    lines, line = [], " " * 12 + "("
    for item in items:
        if len(line) + len(item) + 1 > width and line.strip() != "(":
            lines.append(line.rstrip() + "\n")
            line = " " * 13
        line += item + " "
    return lines + [line.rstrip() + "),\n"]


def main() -> None:
    seen = record_calls()
    with tempfile.TemporaryDirectory() as tmp:
        workloads(Path(tmp))
    forms = source_form(seen)
    text = repr(forms)
    used = sorted({t for t in SCALARS.values() if re.search(rf"\b{t}\b", text)},  # isort's natural order
                  key=lambda t: (re.sub(r"\d", "", t), int(re.sub(r"\D", "", t) or 0)))
    lines = [HEADER.replace("{types}", ", ".join(used))]
    for module, kernels in forms.items():
        lines.append(f"    {module!r}: {{\n")
        for kernel, sigs in kernels.items():
            lines.append(f"        {kernel!r}: [\n")
            for sig in sigs:
                lines += wrapped(sig)
            lines.append("        ],\n")
        lines.append("    },\n")
    lines.append("}\n")
    OUT.write_text("".join(lines))
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
