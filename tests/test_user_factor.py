"""The factor graph is the researcher's API: add your own factor and re-optimise."""
from __future__ import annotations

import gtsam
import numpy as np

from ari_sfm.factors import keys
from ari_sfm.factors.rig_graph import RigGraph
from ari_sfm.geometry import angle_between_deg


def test_prior_on_the_normal_from_a_level(single_scene):
    """A tight prior on the normal (e.g. measured by a level) is honoured by the optimum."""
    truth_n = np.asarray(single_scene.truth["interface"]["normal_world"])
    free = RigGraph.from_dataset(single_scene.dataset, model="ari")
    free_state = free.optimize()
    free_err = angle_between_deg(free_state.normal_world, truth_n)

    problem = RigGraph.from_dataset(single_scene.dataset, model="ari")
    noise = gtsam.noiseModel.Isotropic.Sigma(2, np.radians(0.01))
    problem.graph.push_back(gtsam.PriorFactorUnit3(keys.N, gtsam.Unit3(truth_n), noise))
    state = problem.optimize()
    assert angle_between_deg(state.normal_world, truth_n) < 0.5 * free_err
    assert angle_between_deg(state.normal_world, truth_n) < 0.05
