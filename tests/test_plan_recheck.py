"""The recheck of an accepted plan drawn off the building keeps it by the rule that accepted it.

A registration MFR accepted at its drawing tolerance may pass the judge's map check relatively:
its walls explain less than ``min_map_fit`` of the map, but at least ``MAP_FIT_FLOOR`` and clearly
more than each runner-up placement. The recheck of the grown map retracted such a plan as soon
as its fit was below ``min_map_fit`` (Intel with its real plan: accepted at 205 m, retracted
twice, no prior left at the end). Now the recheck applies the same rule, against the runner-up
placements the registration carries, also after the plan was moved or rescaled.
"""

from __future__ import annotations

import numpy as np

from frslam_graph.config import UpdatesConfig
from frslam_graph.localisation.relocalisation import Relocaliser, RelocaliserParams
from frslam_graph.plan_checks import occupied_points
from frslam_graph.plan_updates.accepted import AcceptedPlan
from frslam_graph.plan_updates.judge import MAP_FIT_FLOOR, RegistrationJudge
from frslam_graph.plan_updates.refiner import _runner_ups
from frslam_graph.registration import Registration
from tests.test_registration import ring_map, synthetic_plan, truth_matrix
from tests.test_update_strategy import rotated_about_centre

ROOMS = ["living", "kitchen", "bath", "corridor", "bed1", "bed2", "closet"]


def _accepted(plan, truth, alternatives):
    details = {
        "drawn_ok": True,
        "drawn_tol_m": 0.2,
        "alternatives": [{"score": 0.5, "matrix": m.tolist()} for m in alternatives],
    }
    reg = Registration.from_matrix(truth, score=0.9, ambiguity=0.3, method="mfr", details=details)
    rel = Relocaliser(reg.apply(plan), RelocaliserParams())
    return AcceptedPlan(0, reg, rel.plan, rel, map_fit=0.4, drawing_tol=0.2)


def test_a_plan_clearly_better_than_its_runner_ups_stays_and_one_that_is_not_goes():
    plan = synthetic_plan()
    truth = truth_matrix(False, 90.0)
    grid = ring_map(plan, truth, ROOMS)
    judge = RegistrationJudge(plan, UpdatesConfig(), RelocaliserParams(), None)
    turned = rotated_about_centre(plan, truth, np.pi / 2.0)
    mirrored = rotated_about_centre(plan, truth, mirror=True)
    shifted = rotated_about_centre(plan, truth, shift=(0.05, 0.0))
    fit = 0.45  # a kept part explaining less than min_map_fit (0.5) of the grown map

    keep = _accepted(plan, truth, [turned, mirrored])
    assert judge.still_clearly_best(None, None, grid, keep, 0.0, fit)
    # a runner-up placement (5 cm off) that explains the map as well: not clearly best
    same = _accepted(plan, truth, [turned, shifted])
    occ = occupied_points(grid)
    assert Relocaliser(Registration.from_matrix(shifted).apply(plan)).fit_points(occ, 0.2) > 0.8 * fit
    assert not judge.still_clearly_best(None, None, grid, same, 0.0, fit)
    # below the floor, or with no runner-up to compare with: retracted as before
    assert not judge.still_clearly_best(None, None, grid, keep, 0.0, MAP_FIT_FLOOR - 0.01)
    assert not judge.still_clearly_best(None, None, grid, _accepted(plan, truth, []), 0.0, fit)


def test_a_moved_plan_keeps_its_runner_ups_moved_alike():
    plan = synthetic_plan()
    truth = truth_matrix(True, 180.0)
    turned = rotated_about_centre(plan, truth, np.pi / 2.0)
    reg = _accepted(plan, truth, [turned]).registration
    move = np.array([[np.cos(0.05), -np.sin(0.05), 0.7], [np.sin(0.05), np.cos(0.05), -0.2], [0.0, 0.0, 1.0]])
    [alt] = _runner_ups(reg, move)["alternatives"]
    assert np.allclose(np.asarray(alt["matrix"]), move @ turned)
    assert alt["score"] == 0.5
    assert _runner_ups(Registration.from_matrix(truth), move) == {"alternatives": []}
