"""Synthetic datasets with exact Snell physics and their truth.

``make_scene(name)`` builds a scenario in memory (a :class:`Scene`: the
dataset a user would hold, with observations, and the truth);
``simulate(name, out_dir)`` writes ``out_dir/dataset/`` (rig.yaml and either
observations.json or rendered PNG images) and ``out_dir/truth.json`` beside
it.  Scenario names and one-line descriptions are in :data:`SCENARIOS`; a
scenario's geometry options are a :class:`ScenarioOverrides`
(``make_scene("binocular", overrides=ScenarioOverrides(num_frames=8))``).

Every pixel comes from :class:`~ari_sfm.models.exact.ExactModel` (Snell's
law at both faces of the plate), never from the paraxial ARI equation the
project calibrates with: a test on these data measures the model, not a
tautology.

Random streams: the geometry of a scenario comes from ``(seed, scenario)``
alone, the noise from a second stream, so ``sigma_px`` and ``image_scale``
never move a pose; ``paper_single`` and ``paper_single_images`` share the
geometry for a seed.
"""
from __future__ import annotations

import logging
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ari_sfm.records import Dataset, Observation
from ari_sfm.simulate.scenarios import REGISTRY, SCENARIOS, ScenarioOverrides, build_geometry
from ari_sfm.simulate.scene import Geometry, image_path, observe, to_dataset, truth_dict

logger = logging.getLogger(__name__)

__all__ = ["SCENARIOS", "ScenarioOverrides", "Scene", "make_scene", "simulate", "images_by_default"]

PLACEHOLDER_ROOT = Path("<simulated>")


@dataclass(frozen=True)
class Scene:
    """A simulated experiment in memory.

    ``dataset``: what a user would hold (observations with noise, no images,
    ``root`` a placeholder).  ``truth``: the ``calibration.json``-form truth
    (model ``truth``).  ``geometry``: the same truth as objects.
    ``exact_observations``: the noise-free records (same order as the dataset's).
    """

    name: str
    dataset: Dataset
    truth: dict  # calibration.json's form (read by ari_sfm.io.parse_calibration), plus the scenario's keys
    geometry: Geometry
    exact_observations: tuple[Observation, ...]


def _rng(name: str, seed: int, stream: int) -> np.random.Generator:
    """Deterministic generator for (seed, scenario family, stream): 0 geometry, 1 noise, 2 images."""
    family = REGISTRY[name].rng_name or name
    return np.random.default_rng([int(seed), zlib.crc32(family.encode()), stream])


def _check_name(name: str) -> None:
    if name not in REGISTRY:
        raise ValueError(f"unknown scenario {name!r}; choose one of {', '.join(SCENARIOS)}")


def images_by_default(name: str) -> bool:
    """Whether ``simulate(name, ...)`` renders images when ``images`` is None.

    Args:
        name: A scenario of :data:`SCENARIOS`.

    Returns:
        True for the scenarios of rendered images (``*_images``, ``*_dots``).

    Raises:
        ValueError: an unknown scenario.
    """
    _check_name(name)
    return REGISTRY[name].images


def make_scene(name: str, seed: int = 0, sigma_px: float = 0.05, overrides: ScenarioOverrides | None = None, *,
               image_scale: float = 1.0, dist: Sequence[float] | None = None) -> Scene:
    """Build scenario ``name`` in memory.

    Args:
        name: A scenario of :data:`SCENARIOS`.
        seed: The random seed: the geometry comes from ``(seed, scenario)`` alone, the noise from a second stream.
        sigma_px: i.i.d. Gaussian noise per pixel coordinate on every record (>= 0).
        overrides: Options of the scenario's geometry, e.g. ``ScenarioOverrides(num_frames=8)`` (None: as
            registered; :func:`~ari_sfm.simulate.scenarios.scenario_options` lists what a scenario accepts).
        image_scale: Scales image size and K (> 0); the geometry and which camera sees what do not change.
        dist: Lens distortion k1 k2 p1 p2 k3 given to every camera (None: none).

    Returns:
        The scene: the dataset a user would hold (noisy observations), its truth, the noise-free records.

    Raises:
        ValueError: an unknown scenario or option, ``image_scale`` <= 0 or ``sigma_px`` < 0.
    """
    _check_name(name)
    image_scale = float(image_scale)
    if not image_scale > 0.0:
        raise ValueError(f"image_scale must be > 0 (got {image_scale})")
    if sigma_px < 0.0:
        raise ValueError(f"sigma_px must be >= 0 (got {sigma_px})")
    geometry = build_geometry(name, _rng(name, seed, 0), overrides).scaled(image_scale)
    if dist is not None:
        geometry = replace(geometry, cameras=tuple(replace(c, dist=np.resize(np.asarray(dist, float), 5))
                                                   for c in geometry.cameras))
    exact = observe(geometry)
    noise_rng = _rng(name, seed, 1)
    noisy = tuple(o if sigma_px == 0.0
                  else replace(o, pixels=o.pixels + noise_rng.normal(0.0, sigma_px, o.pixels.shape))
                  for o in exact)
    dataset = to_dataset(geometry, noisy, PLACEHOLDER_ROOT, seen=exact)
    truth = truth_dict(geometry, name, seed, sigma_px)
    n_cams = {o.camera for o in exact}
    logger.info("scenario %s seed %d: %d cameras, %d records, %d corners", name, seed, len(n_cams),
                len(exact), sum(len(o.ids) for o in exact))
    return Scene(name=name, dataset=dataset, truth=truth, geometry=geometry, exact_observations=exact)


def _pixel_to_target(geometry: Geometry, camera: str, frame_pose, added_mm: float):
    """pixels (N, 2) -> target-plane (x, y) mm of the exact scene ray of each pixel (NaN if missed)."""
    cam = geometry.camera(camera)
    model = geometry.window_of(camera).model(cam, added_mm)
    cam_from_target = cam.cam_from_world.compose(frame_pose)
    R, t = cam_from_target.R, cam_from_target.t

    def pixel_to_target(uv: np.ndarray) -> np.ndarray:
        origins, dirs = model.backproject(np.asarray(uv, float))
        o_t = (origins - t) @ R  # R^T (o - t): ray in the target frame
        d_t = dirs @ R
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = -o_t[:, 2] / d_t[:, 2]
            xy = o_t[:, :2] + lam[:, None] * d_t[:, :2]
        xy[~(lam > 0.0)] = np.nan
        return xy

    return pixel_to_target


def render_images(scene: Scene, dataset_dir: Path, seed: int = 0, supersample: int = 4,
                  noise_sigma: float = 1.0) -> list[Path]:
    """Render one PNG per record of ``scene`` into ``dataset_dir``.

    Args:
        scene: The scene (its noise-free records are rendered).
        dataset_dir: The dataset folder; each image at :func:`~ari_sfm.simulate.scene.image_path` in it.
        seed: The images' noise seed (each image its own stream from it).
        supersample: Samples per pixel side (anti-aliasing).
        noise_sigma: The images' Gaussian noise, grey levels.

    Returns:
        The paths written, in the records' order.

    Raises:
        OSError: an image could not be written.
    """
    import cv2

    from ari_sfm.simulate.render import render_target

    geometry = scene.geometry
    frames = geometry.frames()
    written = []
    for k, o in enumerate(scene.exact_observations):
        rel = image_path(o.set, o.camera, o.frame, o.added_mm)
        f = _pixel_to_target(geometry, o.camera, frames[o.frame], o.added_mm or 0.0)
        img = render_target(geometry.target, f, geometry.camera(o.camera).image_size,
                            supersample=supersample, noise_sigma=noise_sigma,
                            seed=int(np.random.SeedSequence([seed, k]).generate_state(1)[0]))
        path = dataset_dir / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), img):
            raise OSError(f"could not write {path}")
        written.append(path)
        logger.info("rendered %s", rel)
    return written


def simulate(name: str, out_dir: str | Path, seed: int = 0, sigma_px: float = 0.05, images: bool | None = None,
             image_scale: float = 1.0, overrides: ScenarioOverrides | None = None) -> tuple[Path, Path]:
    """Write scenario ``name`` to ``out_dir/dataset/`` and its truth to ``out_dir/truth.json``.

    Without images the dataset holds ``observations.json`` (noisy exact corners). With images it holds PNGs
    under stack/, calib/, recon/ listed in rig.yaml and no observations: the corners must be detected. The
    noise-free corners are written beside the truth as ``truth_observations.json`` (for judging a detector).

    Args:
        name: A scenario of :data:`SCENARIOS`.
        out_dir: The output folder.
        seed: The random seed (:func:`make_scene`).
        sigma_px: Pixel noise per coordinate of the observations.
        images: Render PNG images; None: the scenario's default (the ``*_images`` and ``*_dots`` scenarios).
        image_scale: Scales image size and K.
        overrides: Options of the scenario's geometry (:func:`make_scene`).

    Returns:
        (the dataset folder, truth.json's path).

    Raises:
        ValueError: an unknown scenario or option, a bad number, or images asked of scale16.
    """
    from ari_sfm.io import save_observations, save_rig, write_json_atomic

    _check_name(name)
    images = REGISTRY[name].images if images is None else bool(images)
    if images and name == "scale16":
        raise ValueError("scale16 is observations only (16 cameras x 500 frames of images is not a test set)")
    scene = make_scene(name, seed=seed, sigma_px=sigma_px, overrides=overrides, image_scale=image_scale)
    out_dir = Path(out_dir)
    dataset_dir = out_dir / "dataset"
    dataset_dir.mkdir(parents=True, exist_ok=True)
    stale = dataset_dir / "observations.json"
    if images:
        if stale.exists():  # a previous run's detections must not stand in for the images
            stale.unlink()
        render_images(scene, dataset_dir, seed=seed)
        dataset = to_dataset(scene.geometry, None, dataset_dir, seen=scene.exact_observations, with_images=True)
    else:
        dataset = replace(scene.dataset, root=dataset_dir, rig_path=dataset_dir / "rig.yaml",
                          observations_path=stale)
    save_rig(dataset_dir / "rig.yaml", dataset)  # writes observations.json too when the dataset holds them
    truth_path = out_dir / "truth.json"
    truth = dict(scene.truth, images=images)
    write_json_atomic(truth_path, truth)
    save_observations(out_dir / "truth_observations.json", scene.exact_observations)
    logger.info("wrote %s and %s", dataset_dir, truth_path)
    return dataset_dir, truth_path
