"""Session 27's exact CPU cuts of the MFR registration: the fits iterated together, the local
search's hypotheses scored together and the smaller helpers, each against what it replaces, bit
for bit (tools/README.md, "Session 27")."""

from __future__ import annotations

import copy
import dataclasses
import math
import pickle

import numpy as np
import pytest

from frslam_graph.registration.mfr.coarse import (
    WIDE_AXES,
    WIDE_BEAM,
    WIDE_FACTORS,
    WIDE_POLISH,
    WIDE_SHIFTS,
    Hypothesis,
    _aligned_frame,
    _aspect_ok,
    _axis_trials,
    _placed_mask,
    _top_cells,
    coarse_scores,
    same_placement,
)
from tests.test_registration_cpu import _seen_grid


@pytest.fixture(scope="module")
def scene():
    """A plan model and the observation of a map showing four of its rooms (scaled, turned)."""
    from frslam_graph.registration.mfr.map_side import observe_map
    from frslam_graph.registration.mfr.plan_side import prepare_plan

    plan, truth, grid = _seen_grid(0.35)
    obs = observe_map(grid)
    # the truth in the observation's grid frame (plan -> grid metres)
    to_grid = np.linalg.inv(obs.to_map) @ truth
    return prepare_plan(plan), obs, to_grid


def _starts(pm, obs, to_grid, n: int, seed: int):
    """``n`` refinement starts about the truth (a few off in scale, shift, turn; one flipped)."""
    from frslam_graph.registration.mfr.fine import _fit_start
    from frslam_graph.se2 import to_matrix

    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        off = to_matrix((rng.normal(0, 0.15), rng.normal(0, 0.15), rng.normal(0, 0.05)))
        m = off @ to_grid @ np.diag([1 + rng.normal(0, 0.04), 1 + rng.normal(0, 0.04), 1.0])
        if k == n - 1:
            m = m @ np.diag([1.0, -1.0, 1.0])  # a mirrored start: converges elsewhere, or not at all
        out.append(_fit_start(pm, obs, m, 0.06, [1.5, 4.0, 2.5, 6.0][k % 4], [1500, 300, 700, 120][k % 4])[0])
    return out


def _same_result(a, b) -> None:
    for f in dataclasses.fields(a):
        if f.name == "_matrix":
            continue
        u, v = getattr(a, f.name), getattr(b, f.name)
        if isinstance(u, np.ndarray) or isinstance(v, np.ndarray):
            assert u is not None and v is not None and np.array_equal(u, v, equal_nan=True), f.name
        elif isinstance(u, float) and math.isnan(u):
            assert isinstance(v, float) and math.isnan(v), f.name
        else:
            assert u == v and math.copysign(1.0, u or 0.0) == math.copysign(1.0, v or 0.0), f.name


@pytest.mark.parametrize(
    ("scales", "iterations", "fixed"), [((0.15,), 6, 0), ((0.4, 0.15, 0.05), 8, 1), ((0.05,), 10, 0)]
)
def test_refine_many_equals_refine_start_by_start(scene, scales, iterations, fixed) -> None:
    # the starts stop at different iterations (converged, degenerate): each answer is refine's
    from frslam_graph.registration.refine import refine, refine_many

    pm, obs, to_grid = scene
    starts = _starts(pm, obs, to_grid, 7, seed=len(scales))
    opts = {"delta_sigma": 0.05, "scales": scales, "iterations": iterations, "fixed_delta_stages": fixed}
    got = refine_many(starts, obs.field, **opts)
    for st, g in zip(starts, got, strict=True):
        want = refine(
            st.points,
            st.normals,
            obs.field,
            st.flipped,
            st.theta,
            st.tx,
            st.ty,
            st.sx,
            st.sy,
            delta=st.delta,
            correlation=st.correlation,
            **opts,
        )
        _same_result(g, want)
    assert len({round(g.rms, 9) for g in got}) > 1  # distinct fits, not one repeated


def test_refine_many_of_no_start_and_of_a_start_without_points(scene) -> None:
    from frslam_graph.registration.refine import FitStart, refine, refine_many

    pm, obs, to_grid = scene
    assert refine_many([], obs.field) == []
    empty = FitStart(np.zeros((0, 2)), np.zeros((0, 2)), False, 0.1, 1.0, 2.0, 0.4, 0.45, delta=0.06)
    got = refine_many([empty, *_starts(pm, obs, to_grid, 2, seed=4)], obs.field, scales=(0.15,), iterations=6)
    want = refine(
        empty.points,
        empty.normals,
        obs.field,
        False,
        0.1,
        1.0,
        2.0,
        0.4,
        0.45,
        delta=0.06,
        scales=(0.15,),
        iterations=6,
    )
    _same_result(got[0], want)
    assert got[0].n_points == 0 and got[1].n_points > 0


def test_polish_scales_many_equals_one_placement_at_a_time(scene) -> None:
    from frslam_graph.registration.mfr import fine
    from frslam_graph.registration.mfr.coarse import Hypothesis
    from frslam_graph.registration.mfr.register import DEFAULTS

    pm, obs, to_grid = scene
    opts = dict(DEFAULTS)
    rng = np.random.default_rng(8)
    hs = []
    for k in range(3):
        m = to_grid @ np.diag([1 + 0.06 * (k - 1), 1 - 0.05 * (k - 1), 1.0])
        m[:2, 2] += rng.normal(0, 0.1, 2)
        hs.append(Hypothesis(1 + 2 + 8, 0, False, m, 0.0))
    fine.screen(pm, obs, hs, opts, 0.15)
    assert sum(h.quick > 0 for h in hs) >= 2
    one = copy.deepcopy(hs)
    for h in one:
        fine.polish_scales_many(pm, obs, [h], opts, 0.15)
    fine.polish_scales_many(pm, obs, hs, opts, 0.15)
    for a, b in zip(hs, one, strict=True):
        assert (a.quick, a.placed_iou, a.placed_rooms, a.recall) == (
            b.quick,
            b.placed_iou,
            b.placed_rooms,
            b.recall,
        )
        _same_result(a.refined, b.refined)


def test_rows_dot_in_blocks_is_each_block_as_its_own_product() -> None:
    from frslam_graph.registration.mfr.coarse import rows_dot

    rng = np.random.default_rng(1)
    v = rng.random(11) * 50
    for h, block in ((45, 15), (30, 15), (7, 15), (64, 64), (195 * 3, 195)):
        m = rng.random((h, 11)) * (rng.random((h, 11)) < 0.6)
        got = rows_dot(m, v, block)
        want = np.concatenate([np.asarray(m[i : i + block] @ v) for i in range(0, h, block)])
        assert got.tobytes() == want.tobytes()
        assert rows_dot(m, v).tobytes() == (m @ v).tobytes()


def test_coarse_scores_of_groups_in_blocks_equal_each_group_alone(scene) -> None:
    # the local search scores both hypotheses' trials in one call: each group as if alone
    from frslam_graph.registration.mfr.coarse import coarse_scores
    from frslam_graph.se2 import to_matrix

    pm, obs, to_grid = scene
    rng = np.random.default_rng(2)
    groups = []
    for _ in range(3):
        base = to_matrix((rng.normal(0, 0.3), rng.normal(0, 0.3), rng.normal(0, 0.1))) @ to_grid
        groups.append(
            np.stack(
                [base @ np.diag([1 + 0.05 * rng.normal(), 1 + 0.05 * rng.normal(), 1]) for _ in range(15)]
            )
        )
    masks = [np.full(15, m, dtype=np.uint64) for m in (1 + 2 + 8 + 16, 1 + 2, 511)]
    iou, key = coarse_scores(pm, obs, np.concatenate(groups), np.concatenate(masks), (0.3, 4.0), block=15)
    for g, (mats, mk) in enumerate(zip(groups, masks, strict=True)):
        i1, k1 = coarse_scores(pm, obs, mats, mk, (0.3, 4.0))
        assert iou[15 * g : 15 * (g + 1)].tobytes() == i1.tobytes()
        assert key[15 * g : 15 * (g + 1)].tobytes() == k1.tobytes()
    assert np.ptp(key) > 0


def _old_local_search(pm, obs, hyps, opts) -> None:
    """``coarse.local_search`` as it was (main c7fcc18): hypothesis by hypothesis."""
    from frslam_graph.registration.mfr.coarse import coarse_scores
    from frslam_graph.se2 import rot

    rounds = (((0.85, 0.92, 1.0, 1.08, 1.17), 0.08), ((0.96, 0.98, 1.0, 1.02, 1.04), 0.03))
    for h in hyps:
        angle, bbox = obs.angles[h.angle_index], obs.bboxes[h.angle_index]
        rm = np.eye(3)
        rm[:2, :2] = rot(angle)
        c = rot(-angle) @ obs.centroid
        ext = bbox[2:] - bbox[:2]
        for factors, shift in rounds:
            for axis in (0, 1):
                f = np.repeat(np.array(factors), 3)
                sh = np.tile(np.array([-shift, 0.0, shift]), len(factors))
                d = np.broadcast_to(np.eye(3), (len(f), 3, 3)).copy()
                d[:, axis, axis] = f
                d[:, axis, 2] = c[axis] * (1.0 - f) + sh * ext[axis]
                mats = rm @ d @ rm.T @ h.matrix
                iou, key = coarse_scores(
                    pm, obs, mats, np.full(len(mats), h.mask, dtype=np.uint64), opts["door_width_m"]
                )
                top = int(np.argmax(key))
                if float(key[top]) > h.key:
                    h.matrix, h.key, h.coarse_iou = mats[top], float(key[top]), float(iou[top])


def test_local_search_of_two_hypotheses_together_equals_one_by_one(scene) -> None:
    from frslam_graph.registration.mfr import coarse
    from frslam_graph.registration.mfr.register import DEFAULTS
    from frslam_graph.registration.subsets import connected_subsets

    pm, obs, _ = scene
    opts = dict(DEFAULTS)
    masks = connected_subsets(pm.adjacency, max_per_level=3000)
    hyps, _ = coarse.search(pm, obs, masks, {**opts, "search_below_iou": 0.0})  # no search inside
    assert len(hyps) >= 3
    pair = [copy.deepcopy(hyps[0]), copy.deepcopy(hyps[2])]
    pair[1].matrix = pair[1].matrix @ np.diag([1.1, 0.93, 1.0])  # a start the search moves
    want = copy.deepcopy(pair)
    coarse.local_search(pm, obs, pair, opts)
    _old_local_search(pm, obs, want, opts)
    for a, b in zip(pair, want, strict=True):
        assert a.matrix.tobytes() == b.matrix.tobytes() and a.key == b.key and a.coarse_iou == b.coarse_iou
    assert any(not np.array_equal(a.matrix, b.matrix) for a, b in zip(pair, hyps[:3:2], strict=True))


def test_exit_share_is_the_mean_of_the_exits_near_an_opening() -> None:
    from frslam_graph.registration.mfr.coarse import exit_share

    rng = np.random.default_rng(4)
    d = rng.random((9, 7)) * 8
    scale = rng.random(9) * 0.1 + 0.02
    for tol in (0.1, 0.5):
        want = 0.5 + 0.5 * (d < (np.maximum(tol, 0.3) / scale + 0.25)[:, None]).mean(axis=1)
        assert exit_share(d, scale, tol, 0.25).tobytes() == want.tobytes()
        # on a column slice (the exits after the wall cells of one lookup), the same
        wide = np.concatenate([rng.random((9, 5)), d], axis=1)
        assert exit_share(wide[:, 5:], scale, tol, 0.25).tobytes() == want.tobytes()


def test_sample_free_equals_sample_and_free_at() -> None:
    from frslam_graph.registration.refine import DistanceField

    rng = np.random.default_rng(5)
    free = rng.random((60, 80)) < 0.6
    for origin in ((0.0, 0.0), (-1.25, 0.4)):
        f = DistanceField.from_masks(free, 0.05, origin)
        x, y, fx, fy = (rng.uniform(-1.6, 4.5, 400) for _ in range(4))
        val, gx, gy, inside, kn = f.sample_free(x, y, fx, fy)
        want = f.sample(x, y)
        for a, b in zip((val, gx, gy, inside), want, strict=True):
            assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
        assert kn.tobytes() == f.free_at(fx, fy).tobytes()


def test_cells_without_a_zero_origin_equal_the_subtraction() -> None:
    from frslam_graph.registration.refine import _offset_scaled

    rng = np.random.default_rng(6)
    v = rng.normal(0, 3, 500)
    v[:4] = [-0.0, 0.0, np.nan, -np.inf]
    for o in (0.0, -0.0, 0.35):
        want = (v - o) * 20.0
        got = _offset_scaled(v, o, 20.0)
        assert np.array_equal(got, want, equal_nan=True) and np.array_equal(np.signbit(got), np.signbit(want))
        assert got is not v


def test_refine_result_matrix_kept_while_its_parameters_stay() -> None:
    from frslam_graph.registration.refine import RefineResult
    from frslam_graph.registration.result import matrix_from_params

    pre = np.eye(3)
    pre[:2, :2] = [[0.8, -0.6], [0.6, 0.8]]
    r = RefineResult(True, 0.3, 1.0, -2.0, 0.4, 0.45, 0.05, 0.01, 0.9, 300, None, None, pre)
    want = matrix_from_params(True, 0.3, 0.4, 0.45, 1.0, -2.0) @ pre
    m = r.matrix
    assert m.tobytes() == want.tobytes()
    m[0, 0] = 99.0  # a copy: the next one is unchanged
    assert r.matrix.tobytes() == want.tobytes()
    r.theta = -0.0  # a parameter set again: computed again
    assert r.matrix.tobytes() == (matrix_from_params(True, -0.0, 0.4, 0.45, 1.0, -2.0) @ pre).tobytes()
    r.pre = None
    assert r.matrix.tobytes() == matrix_from_params(True, -0.0, 0.4, 0.45, 1.0, -2.0).tobytes()
    moved = dataclasses.replace(r, tx=5.0)
    assert moved.matrix[0, 2] == 5.0
    back = pickle.loads(pickle.dumps(r))
    assert back._matrix is None and back == r and back.matrix.tobytes() == r.matrix.tobytes()


def test_fixed_rings_pieces_equal_np_split() -> None:
    from frslam_graph.registration.mfr.plan_side import FIX, _fixed_rings

    rng = np.random.default_rng(7)
    rings = [rng.random((k, 2)) * 30 for k in (4, 7, 3, 12)]
    a, t = np.array([[0.4, -0.1], [0.12, 0.38]]), np.array([3.0, -1.5])
    q = np.round((np.concatenate([r @ a.T for r in rings]) + t) * FIX).astype(np.int32)
    want = [v.reshape(-1, 1, 2) for v in np.split(q, np.cumsum([len(r) for r in rings])[:-1])]
    got = _fixed_rings(rings, a, t)
    assert len(got) == len(want) and all(
        g.tobytes() == w.tobytes() and g.shape == w.shape for g, w in zip(got, want, strict=True)
    )
    assert _fixed_rings([], a, t) == []


def test_plan_and_map_constants_kept_are_their_sums(scene) -> None:
    pm, obs, _ = scene
    assert pm.inner_counts.tobytes() == pm.inner_onehot.sum(axis=0).tobytes()
    assert obs.footprint_cells == int(np.count_nonzero(obs.footprint))
    assert obs.any_unexplored == bool(obs.unexplored.any())


def _old_wide_search(
    pm,
    obs,
    seeds: list[Hypothesis],
    opts: dict,
    tol: float,
    limit: int,
    check: bool = False,
    polish_best: int | None = None,
) -> list[Hypothesis]:
    """``coarse.wide_search`` as it was (main c7fcc18): seed by seed, beam by beam."""
    door, cover, points = opts["door_width_m"], opts["min_cover"], opts["first_pass_points"]
    full = np.uint64((1 << len(pm.ids)) - 1) if len(pm.ids) < 64 else np.uint64(2**64 - 1)

    def score(mats: np.ndarray, pts, tl=None) -> np.ndarray:
        _, k = coarse_scores(pm, obs, mats, np.full(len(mats), full), door, pts, tl, matched_cover=cover)
        return np.where(_aspect_ok(pm, mats, opts["max_aspect"]), k, 0.0)

    width = 1 if check else WIDE_BEAM
    shifts = WIDE_SHIFTS[3:-3] if check else WIDE_SHIFTS  # a refined placement: +-12.5 %
    last_points = opts["quick_points"] if check else None
    found: list[tuple[float, np.ndarray, int]] = []
    beams: list[tuple[float, np.ndarray, int]] = []
    for si, seed in enumerate(seeds):
        rm, c, ext = _aligned_frame(obs, seed.angle_index)
        beam = [(float(score(seed.matrix[None], points)[0]), seed.matrix)]
        for axis in WIDE_AXES[:2] if check else WIDE_AXES:
            grown = list(beam)
            for _, m in beam:
                mats = _axis_trials(m, rm, c, ext, axis, WIDE_FACTORS, shifts)
                k = score(mats, points)
                grown += [
                    (float(k[i]), mats[i]) for i in _top_cells(k, (len(WIDE_FACTORS), len(shifts)), width)
                ]
            grown.sort(key=lambda t: -t[0])
            beam = []
            for k_, m in grown:
                if not any(same_placement(m, b, obs) for _, b in beam):
                    beam.append((k_, m))
                if len(beam) >= width:
                    break
        if check and np.allclose(beam[0][1], seed.matrix):
            continue  # no other scale or shift on the grid scores better: nothing to polish
        beams.extend((k_, m, si) for k_, m in beam)
    if polish_best is not None:  # only the best placements of all seeds' grids are polished
        beams = sorted(beams, key=lambda t: -t[0])[:polish_best]
    for _, m, si in beams:
        rm, c, ext = _aligned_frame(obs, seeds[si].angle_index)
        for stage, (half, nf, shift, ns, tmul) in enumerate(WIDE_POLISH):
            factors = np.exp(np.linspace(-math.log(half), math.log(half), nf))
            pts = last_points if stage == len(WIDE_POLISH) - 1 else points
            tl = None if tmul is None else tmul * tol
            for axis in (0, 1):
                mats = np.concatenate(
                    [m[None], _axis_trials(m, rm, c, ext, axis, factors, np.linspace(-shift, shift, ns))]
                )
                m = mats[int(np.argmax(score(mats, pts, tl)))]
        found.append((float(score(m[None], last_points, WIDE_POLISH[-1][4] * tol)[0]), m, si))
    found.sort(key=lambda t: -t[0])
    out: list[Hypothesis] = []
    for k_, m, si in found:
        if k_ <= 0.0 or any(same_placement(m, h.matrix, obs) for h in out):
            continue
        iou, key = coarse_scores(pm, obs, m[None], np.array([full]), door, matched_cover=cover)
        out.append(
            Hypothesis(
                _placed_mask(pm, obs, m, cover),
                0,
                False,
                m,
                0.0,
                seeds[si].angle_index,
                coarse_iou=float(iou[0]),
                key=float(key[0]),
            )
        )
        if len(out) >= limit:
            break
    return out


@pytest.mark.parametrize("check", [False, True])
def test_wide_search_of_all_seeds_together_equals_seed_by_seed(scene, check: bool) -> None:
    from frslam_graph.registration.mfr import coarse
    from frslam_graph.registration.mfr.register import DEFAULTS
    from frslam_graph.registration.subsets import connected_subsets

    pm, obs, _ = scene
    opts = dict(DEFAULTS)
    masks = connected_subsets(pm.adjacency, max_per_level=3000)
    hyps, rotations = coarse.search(pm, obs, masks, opts)
    seeds = [hyps[0], *rotations[:3]] if not check else [hyps[1]]
    seeds += coarse.turned_seeds(hyps[0], obs)[:2]
    for polish_best in (None, 3):
        got = coarse.wide_search(pm, obs, seeds, opts, 0.15, 3, check=check, polish_best=polish_best)
        want = _old_wide_search(pm, obs, seeds, opts, 0.15, 3, check=check, polish_best=polish_best)
        assert len(got) == len(want) > 0
        for a, b in zip(got, want, strict=True):
            assert a.matrix.tobytes() == b.matrix.tobytes()
            assert (a.mask, a.key, a.coarse_iou, a.angle_index) == (
                b.mask,
                b.key,
                b.coarse_iou,
                b.angle_index,
            )
