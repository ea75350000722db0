"""The researcher's path is the production path: docs/RESEARCH.md's example runs, user factors join
every calibrate stage, the graph types are exported, and the graph says what it needs."""
from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import gtsam
import numpy as np
import pytest

import ari_sfm
from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.factors import keys
from ari_sfm.factors.rig_graph import RigGraph, RigState
from ari_sfm.geometry import Pose, angle_between_deg

ROOT = Path(__file__).resolve().parents[1]


def test_research_doc_example_runs():
    """Every python block of docs/RESEARCH.md, in order, in one namespace; then its numbers."""
    text = (ROOT / "docs" / "RESEARCH.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) >= 2
    ns: dict = {}
    for block in blocks:
        exec(compile(block, "docs/RESEARCH.md", "exec"), ns)
    u = ns["cal"].uncertainty
    assert u.sigma_px == pytest.approx(0.05, rel=0.1)  # the simulated corner noise, estimated
    graph, cov = ns["graph"], ns["cov"]
    assert graph.sigma_px == pytest.approx(0.05, rel=0.1)
    d = np.array([1.0, -1.0, 0.0, 0.0])  # the square-pixel factor holds fx - fy to its 0.01 px
    assert np.sqrt(d @ cov[keys.K(0)] @ d) < 0.011
    assert ns["fx_std_px"] > 0.1  # while fx itself is known to the images' precision only
    assert 0.0 < ns["normal_std_deg"] < 0.05  # the images and the 0.05 deg level together
    assert angle_between_deg(ns["state"].normal_world, ns["level"]) < 0.03


def test_extra_factors_join_every_stage(single_scene):
    truth = np.asarray(single_scene.truth["interface"]["normal_world"])
    level = gtsam.Unit3(truth).retract(np.radians([0.2, 0.0]))  # a tight prior 0.2 deg off the truth
    prior = gtsam.PriorFactorUnit3(keys.N, level, gtsam.noiseModel.Isotropic.Sigma(2, np.radians(1e-4)))
    stages = []

    def factors(graph: RigGraph):
        stages.append(graph.model)
        return [prior]

    cal = calibrate(single_scene.dataset, model="exact", extra_factors=factors, uncertainty=False)
    assert set(stages) == {"ari", "exact"}  # every stage (and its re-weighted re-solve)
    assert angle_between_deg(cal.normal_world, level.point3()) < 1e-3
    listed = calibrate(single_scene.dataset, model="exact", extra_factors=[prior], uncertainty=False)
    assert angle_between_deg(listed.normal_world, cal.normal_world) < 1e-9
    ref = calibrate(single_scene.dataset, model="exact", extra_factors=[prior], uncertainty=False, backend="gtsam")
    assert angle_between_deg(ref.normal_world, cal.normal_world) < 1e-6
    np.testing.assert_allclose(ref.cameras["cam0"].K, cal.cameras["cam0"].K, rtol=1e-8)
    with pytest.raises(ValueError, match="extra_factors"):
        calibrate(single_scene.dataset, model="pinhole", extra_factors=[prior])


def test_sigma_px_given_or_estimated(single_scene, single_exact):
    """The images' sigma: estimated by default (the simulated 0.05 px), or given; the marginals scale with it."""
    est = single_exact.uncertainty.sigma_px
    assert est == pytest.approx(0.05, rel=0.1)
    stage_sigma = {k: s["sigma_px"] for k, s in single_exact.optimizer.to_json().items()}
    assert stage_sigma == {"ari": 1.0, "exact": 1.0}  # nothing to re-weight without priors: each stage at 1 px
    given = calibrate(single_scene.dataset, model="exact", sigma_px=0.1)
    assert {s["sigma_px"] for s in given.optimizer.to_json().values()} == {0.1}
    u, u_est = given.uncertainty, single_exact.uncertainty
    assert u.sigma_px == 0.1
    assert u.normal_deg == pytest.approx(u_est.normal_deg * 0.1 / est, rel=1e-3)
    assert u.cameras["cam0"].intrinsics["fx"] == pytest.approx(u_est.cameras["cam0"].intrinsics["fx"] * 0.1 / est,
                                                               rel=1e-3)
    with pytest.raises(ValueError, match="sigma_px"):
        calibrate(single_scene.dataset, model="ari", sigma_px=0.0)


def test_from_dataset_detects_corners_of_an_image_only_dataset():
    dataset = ari_sfm.load_dataset(ROOT / "datasets" / "sample")
    assert dataset.observations is None
    rg = RigGraph.from_dataset(dataset)
    assert len(rg.factor_data) == 18  # 12 calibration + 6 stacking images
    assert 0.0 < rg.sigma_px < 0.2


def test_camera_zero_is_the_world(single_scene):
    rg = RigGraph.from_dataset(single_scene.dataset, sigma_px=1.0)
    assert not rg.values.exists(keys.C(0))  # no pose variable for camera 0
    name = rg.camera_names[0]
    moved = replace(rg.base_state, cam_from_world={name: Pose(np.eye(3), np.array([1.0, 0.0, 0.0]))})
    ds = single_scene.dataset
    with pytest.raises(ValueError, match="world"):
        RigGraph.build(ds.observations, ds.target, ds.interface, ds.camera_names, moved)


def test_graph_types_are_exported():
    assert ari_sfm.RigGraph is RigGraph and ari_sfm.RigState is RigState and ari_sfm.keys is keys
    from ari_sfm.factors.uncertainty import marginal_covariances

    assert ari_sfm.marginal_covariances is marginal_covariances
    with pytest.raises(AttributeError):
        ari_sfm.no_such_name  # noqa: B018
