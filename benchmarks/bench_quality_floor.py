"""The quality gate's floor on every kind of target: the exact model's fit against the floor.

    python benchmarks/bench_quality_floor.py            # all cases, ~3 min on 2 cores
    python benchmarks/bench_quality_floor.py --only ptv  # the cases whose name contains 'ptv'

For each case (exact-physics simulations: planar boards with stacking, without it, under water, 3D bodies
under water behind a window close to the cameras, 15 mm deep or 40 mm, one view or three, lens k1, pixels
quantised to 0.5 px as OpenPTV's, a multi-plane body whose planes were each placed with an error but
declared as one rigid body; and deliberately wrong cases: a declared window turned, a wrong medium index,
a lens not modelled), ``calibrate(model="exact")`` with the default options (a declared plane and fixed
focal lengths where the case says), then prints:

- ``truth``: the robust RMSE of the data against the true model (the noise as it is: the target);
- ``floor``: :func:`ari_sfm.calibration.quality.corner_floor` (what the data allow: a free map per view);
- ``fit``: the calibration's robust RMSE, ``fit/floor``, the allowance and the gate's verdict;
- the floor's time (ms, compiled, the least of 5: the machine is shared).
"""
from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from ari_sfm.calibration.calibrate import CalibrationOptions, calibrate
from ari_sfm.calibration.quality import corner_floor, robust_rmse_px
from ari_sfm.errors import AriSfmError
from ari_sfm.geometry import rotation_from_rotvec
from ari_sfm.records import Dataset, Target
from ari_sfm.simulate import PLACEHOLDER_ROOT, make_scene
from ari_sfm.simulate.particles import ParticleSimOptions, _rig_a, _rng as particles_rng
from ari_sfm.simulate.scenarios import build_geometry, ptv_misplaced
from ari_sfm.simulate.scene import Geometry, observe, to_dataset

K1 = [-0.05, 0.0, 0.0, 0.0, 0.0]


@dataclass(frozen=True)
class Case:
    name: str
    dataset: Dataset
    exact: tuple | None  # the noise-free observations (None: not known)
    options: CalibrationOptions


def _with_noise(geometry: Geometry, sigma: float, seed: int, step: float | None = None,
                true_target: Target | None = None):
    """(dataset, exact observations) of ``geometry`` observed with Gaussian noise ``sigma`` and pixels rounded to
    ``step``; ``true_target``: where the body's points really are (the dataset declares ``geometry.target``)."""
    exact = observe(geometry if true_target is None else replace(geometry, target=true_target))
    rng = np.random.default_rng(seed + 7919)
    noisy = tuple(replace(o, pixels=o.pixels + rng.normal(0.0, sigma, o.pixels.shape)) for o in exact)
    return to_dataset(replace(geometry, pixel_step_px=step), noisy, PLACEHOLDER_ROOT, seen=exact), exact


def particles_geometry(seed: int = 0, views: int = 3, k1: tuple[float, float] | None = None) -> Geometry:
    """The particle experiment's calibration rig (4 cameras, a 3-level 40 mm deep body behind 10 mm of glass in
    water, ``views`` views); lens k1 drawn per camera in ``k1``."""
    geometry, _ = _rig_a(ParticleSimOptions(seed=seed, calibration_frames=views), particles_rng(seed, 0))
    if k1 is not None:
        ks = np.random.default_rng(seed).uniform(*k1, len(geometry.cameras))
        geometry = replace(geometry, cameras=tuple(replace(c, dist=np.array([k, 0.0, 0.0, 0.0, 0.0]))
                                                   for c, k in zip(geometry.cameras, ks)))
    return geometry


def _scene(name: str, sigma: float = 0.05, seed: int = 0, dist: list[float] | None = None) -> tuple[Dataset, tuple]:
    scene = make_scene(name, seed=seed, sigma_px=sigma, dist=dist)
    return scene.dataset, scene.exact_observations


def _turned(dataset: Dataset, deg: float) -> Dataset:
    plane = dataset.interface.plane
    R = rotation_from_rotvec(np.radians(deg) * np.array([1.0, 0.0, 0.0]))
    return replace(dataset, interface=replace(dataset.interface, plane=replace(plane, normal=R @ plane.normal)))


def _medium(dataset: Dataset, index: float) -> Dataset:
    return replace(dataset, interface=replace(dataset.interface, medium_index=index))


def cases(seed: int = 0) -> list[tuple[str, Callable[[], Case]]]:
    """(name, builder) of every case (built lazily)."""
    fixed = CalibrationOptions(fix_intrinsics=True, uncertainty=False)

    def scene(label, name, options=None, transform=None, sigma=0.05, dist=None):
        def build():
            ds, exact = _scene(name, sigma, seed, dist)
            return Case(label, transform(ds) if transform else ds, None if transform else exact,
                        options or CalibrationOptions(uncertainty=False))
        return label, build

    def ptv_placed(label, shift, tilt, transform=None):
        def build():
            geometry = build_geometry("ptv_multiplane", np.random.default_rng([seed, 11]))
            moved = ptv_misplaced(geometry.target, shift, tilt, np.random.default_rng([seed, 13]))
            ds, exact = _with_noise(geometry, 0.0, seed, 0.5, moved)
            return Case(label, transform(ds) if transform else ds, None, fixed)
        return label, build

    def particles(label, views=3, k1=None, step=None, options=None, transform=None):
        def build():
            ds, exact = _with_noise(particles_geometry(seed, views, k1), 0.05, seed, step)
            return Case(label, transform(ds) if transform else ds, None if transform else exact,
                        options or CalibrationOptions(uncertainty=False))
        return label, build

    return [
        scene("paper_single (board, stacking)", "paper_single"),
        scene("paper_single k1 -0.05", "paper_single", dist=K1),
        scene("binocular", "binocular"),
        scene("binocular_underwater", "binocular_underwater"),
        scene("binocular_underwater_oblique (no stacking)", "binocular_underwater_oblique"),
        scene("arc4", "arc4"),
        scene("body3d_water (40 mm deep)", "body3d_water"),
        scene("body3d_water k1 -0.05", "body3d_water", dist=K1),
        scene("body3d_shallow (15 mm deep)", "body3d_shallow"),
        scene("body3d_shallow k1 -0.05", "body3d_shallow", dist=K1),
        scene("ptv_multiplane (0.5 px quantised)", "ptv_multiplane", fixed, sigma=0.0),
        scene("ptv_multiplane noise 0.05 + quantised", "ptv_multiplane", fixed),
        particles("particles body, 3 views"),
        particles("particles body, 1 view", views=1),
        particles("particles body k1 -0.03..-0.06", k1=(-0.06, -0.03)),
        particles("particles body quantised 0.5 px", step=0.5),
        ptv_placed("ptv planes misplaced 0.05 mm 0.02 deg", 0.05, 0.02),
        ptv_placed("ptv planes misplaced 0.1 mm 0.05 deg", 0.1, 0.05),
        ptv_placed("ptv planes misplaced 0.2 mm 0.1 deg", 0.2, 0.1),
        scene("WRONG ptv declared window turned 10 deg", "ptv_multiplane", fixed, lambda d: _turned(d, 10.0),
              sigma=0.0),
        scene("WRONG ptv declared window turned 15 deg", "ptv_multiplane", fixed, lambda d: _turned(d, 15.0),
              sigma=0.0),
        scene("WRONG ptv medium index 1.46 (true 1.333)", "ptv_multiplane", fixed, lambda d: _medium(d, 1.46),
              sigma=0.0),
        scene("WRONG body3d_water medium 1.46", "body3d_water", None, lambda d: _medium(d, 1.46)),
        scene("WRONG body3d_water medium 1.2", "body3d_water", None, lambda d: _medium(d, 1.2)),
        particles("WRONG particles medium 1.46", transform=lambda d: _medium(d, 1.46)),
        ptv_placed("WRONG ptv misplaced 0.1 mm, medium 1.46", 0.1, 0.05, lambda d: _medium(d, 1.46)),
        particles("WRONG particles k1, --no-distortion", k1=(-0.06, -0.03),
                  options=CalibrationOptions(distortion=False, uncertainty=False)),
    ]


def truth_rmse(case: Case) -> float | None:
    """The robust RMSE of the data against the noise-free pixels (None: not known)."""
    if case.exact is None:
        return None
    exact = {(o.camera, o.set, o.frame, o.added_mm): o.pixels for o in case.exact}
    return robust_rmse_px(o.pixels - exact[(o.camera, o.set, o.frame, o.added_mm)] for o in case.dataset.observations
                          if o.set in ("calibration", "stacking"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="", help="run the cases whose name contains this")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"{'case':44s} {'truth':>7s} {'floor':>7s} {'fit':>7s} {'fit/floor':>9s} {'allowed':>8s}  verdict  floor ms")
    for name, build in cases(args.seed):
        if args.only not in name:
            continue
        case = build()
        floor = corner_floor(case.dataset)
        times = []
        for _ in range(5):
            t = time.perf_counter()
            corner_floor(case.dataset)
            times.append(time.perf_counter() - t)
        truth = truth_rmse(case)
        try:
            q = calibrate(case.dataset, model="exact", options=case.options).quality
        except AriSfmError as exc:
            print(f"{name:44s} {'' if truth is None else f'{truth:7.4f}':>7s} {floor.rmse_px:7.4f}  error: "
                  f"{exc.message[:60]}")
            continue
        verdict = "ok" if q.ok else "FAILED"
        starts = "" if q.starts == ("default",) else f" (starts: {', '.join(q.starts)})"
        print(f"{name:44s} {'' if truth is None else f'{truth:7.4f}':>7s} {floor.rmse_px:7.4f} {q.robust_rmse_px:7.4f} "
              f"{q.robust_rmse_px / floor.rmse_px:9.2f} {q.allowance_px:8.4f}  {verdict:7s} {1e3 * min(times):6.2f}"
              f"{starts}", flush=True)


if __name__ == "__main__":
    main()
