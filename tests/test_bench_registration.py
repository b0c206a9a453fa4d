"""tools/bench_registration.py through Dask distributed: the rows of a LocalCluster of two worker
processes equal those of the plain loop, in task order; an unreachable scheduler is one line."""

from __future__ import annotations

import pytest
from conftest import load_tool

TIMING = {"time_s", "cpu_s", "sim_s"}


@pytest.fixture(scope="module")
def bench():
    return load_tool("bench_registration")


def tiny_sweep(data) -> list[dict]:
    """Two R2V plans and one PRBonn distortion, 90° steps, one 50 % map each, both MFRs: 6 rows."""
    plans, _ = load_tool("bench_registration").select_plans(data, 2, seed=0)
    common = {"rotset": "step90", "completeness": [50], "methods": ["paper", "mfr"], "seed": 0}
    tasks = [{"kind": "r2v", "path": str(p), "plan_index": i, **common} for i, p in enumerate(plans)]
    return tasks + [{"kind": "prbonn", "data": str(data), "index": 0, **common}]


@pytest.mark.slow
def test_local_cluster_gives_the_sequential_rows(bench, shared_data):
    tasks = tiny_sweep(shared_data)
    seq, seq_errors = bench.run_tasks(tasks, workers=1)
    par, par_errors = bench.run_tasks(tasks, workers=2)
    assert seq_errors == par_errors == []
    assert len(seq) == 6
    assert [r["case"] for r in seq] == [r["case"] for r in par]  # task order, not finishing order
    strip = [{k: v for k, v in r.items() if k not in TIMING} for r in seq]
    assert strip == [{k: v for k, v in r.items() if k not in TIMING} for r in par]


def test_unreachable_scheduler_is_one_line_and_exit_2(bench, tmp_path, capsys, monkeypatch):
    import _sweep  # the module bench_registration imported (tools/ is on sys.path now)

    monkeypatch.setattr(_sweep, "CONNECT_TIMEOUT_S", 1.0)
    args = ["--data", str(tmp_path), "--plans", "1", "--prbonn", "0", "--completeness", "50"]
    code = bench.main(
        [*args, "--methods", "paper", "--rotations", "step90", "--scheduler", "tcp://127.0.0.1:9"]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith("error: --scheduler tcp://127.0.0.1:9: no Dask scheduler answers there")
