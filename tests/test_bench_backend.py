"""tools/bench_backend.py's floor-plan table: the 'wrong' mode over several corruption seeds (a
house counts by its median), and corrupted registrations that were accepted are counted."""

from __future__ import annotations

from argparse import Namespace
from types import SimpleNamespace

import pytest
from conftest import load_tool


@pytest.fixture(scope="module")
def bench():
    return load_tool("bench_backend")


def row(mode, ate, **extra):
    base = {"regime": "C", "house": "h0", "rooms": 5, "route_m": 210.0, "scans": 2000, "mode": mode}
    base.update(ate=ate, run_s=1.0, xrt=100.0, reg_acc=1, reg_tried=2)
    base.update(prior_added=10, prior_rejected=0, prior_removed=1)
    base.update(extra)
    return base


def test_wrong_mode_counts_a_house_by_its_median_over_seeds(bench):
    clean = [row("none", 0.5), row("plan", 0.010)]
    # one unlucky seed (1.5x) of three: the house's median ratio is 1.05, within 10 %
    wrong = [
        row("wrong", a, corrupted=1, reg_calls=8, wseed=s, leaked=k)
        for a, s, k in ((0.015, 0, 0), (0.0105, 1000, 0), (0.0098, 2000, 1))
    ]
    args = Namespace(length=200.0, speed=1.0, wrong_seeds=3, regimes=["C"])
    text = bench.priors_section(clean + wrong, [], args)
    assert "| 0.011 (3/24, 1) | 1.50/1.05/0.98 |" in text  # median ATE 0.0105
    assert (
        "ATE within 10 % of the clean run: 1/1 houses (median over 3 corruption seeds; single runs 2/3)"
        in text
    )
    assert "corrupted registrations accepted: 1 " in text
    # a single unlucky seed decides alone
    text = bench.priors_section(
        [*clean, wrong[0]], [], Namespace(length=200.0, speed=1.0, wrong_seeds=1, regimes=["C"])
    )
    assert "ATE within 10 % of the clean run: 0/1 houses;" in text


def test_leaked_pairs_registration_decisions_with_corruption_marks(bench):
    def event(kind, accepted):
        return SimpleNamespace(kind=kind, accepted=accepted)

    log = [
        event("register", False),
        event("relocalise", True),
        event("register", True),
        event("registration_replaced", True),
        event("prior_added", True),
    ]
    upd = SimpleNamespace(log=log)
    assert bench._leaked(upd, [True, False, True]) == 1  # the replacement was a corrupted one
    assert bench._leaked(upd, [True, True, False]) == 1
    assert bench._leaked(upd, [True, False]) == -1  # the log does not pair with the calls


@pytest.mark.parametrize(
    ("worker", "label"),
    [(True, "odometry worker + backend, one house at a time"), (False, "one core, sequential")],
)
def test_real_time_row_says_how_the_runs_were_made(bench, worker, label):
    rows = [row("none", 0.5, odometry_worker=worker), row("plan", 0.010, odometry_worker=worker)]
    text = bench.priors_section(rows, [], Namespace(length=200.0, speed=1.0, wrong_seeds=1, regimes=["C"]))
    assert f"| median x real time ({label}) | 100.0 | 100.0 |" in text


def test_latency_rows_summarise_each_runs_per_scan_latency(bench):
    lat = {"lat_median_ms": 4.0, "lat_p99_ms": 18.0, "lat_max_ms": 90.0, "lat_over_20ms": 12}
    rows = [
        row("none", 0.5, **lat),
        row("none", 0.5, house="h1", **{**lat, "lat_p99_ms": 22.0, "lat_max_ms": 40.0, "lat_over_20ms": 30}),
        row("plan", 0.010, **{**lat, "lat_max_ms": 700.0}),
        row("plan", 0.010, house="h1", **lat),
    ]
    text = bench.priors_section(rows, [], Namespace(length=200.0, speed=1.0, wrong_seeds=1, regimes=["C"]))
    assert "| per-scan latency ms, median of the runs' medians | 4.0 | 4.0 | — | — |" in text
    assert "| per-scan latency ms, median of the runs' p99 | 20.0 | 18.0 | — | — |" in text
    assert "| per-scan latency ms, worst run's max | 90.0 | 700.0 | — | — |" in text
    assert "| scans over 20 ms, median of the runs | 21.0 | 12.0 | — | — |" in text


def fake_house(task):
    """A house that is skipped when its plan says so; one row naming the plan and its seed."""
    name = str(task["plan"])
    skip = "not routable" if name.startswith("bad") else None
    return {"plan": name, "skip": skip, "rows": [] if skip else [{"house": name, "seed": task["seed"]}]}


@pytest.fixture
def fake_houses(bench, monkeypatch):
    monkeypatch.setattr(bench, "house_task", fake_house)  # pickled by value with run_houses' globals
    monkeypatch.setattr(bench, "candidate_plans", lambda: ["h0", "bad1", "h2", "h3", "bad4", "h5", "h6"])


@pytest.mark.slow
def test_houses_through_dask_are_the_plain_loops(bench, fake_houses):
    # 4 houses wanted: the 2 skipped plans are replaced by the next ones in the order
    loop = bench.run_houses(4, 1, ["A"], 200.0, 1.0, ["none"])
    dask = bench.run_houses(4, 2, ["A"], 200.0, 1.0, ["none"])
    rows, skipped, cut = loop
    assert [r["house"] for r in rows] == ["h0", "h2", "h3", "h5"] and cut == 0
    assert skipped == [("bad1", "not routable"), ("bad4", "not routable")]
    key = lambda r: r["house"]  # noqa: E731
    assert sorted(dask[0], key=key) == sorted(rows, key=key)  # finishing order may differ
    assert sorted(dask[1]) == skipped and dask[2] == 0


def test_time_budget_starts_no_more_houses(bench, fake_houses):
    rows, skipped, cut = bench.run_houses(4, 1, ["A"], 200.0, 1.0, ["none"], budget_s=0.0)
    assert [r["house"] for r in rows] == ["h0"] and skipped == [] and cut == 3
