"""Bench trials on worker processes (app/trial_pool.py): the same results as in one process, errors raised."""

from __future__ import annotations

import json

import pytest

from app.commands_bench import BENCH_CONTEXT_KEYS
from app.trial_pool import run_pooled
from main import main


def _setup(recipe: dict) -> int:
    return int(recipe["base"])


def _square_plus(base: int, item: int) -> tuple[int, int]:
    if item < 0:
        raise ValueError(f"bad item {item}")
    return item, base + item * item


def test_every_item_runs_once_with_its_workers_setup():
    out = sorted(run_pooled(list(range(7)), 2, _setup, {"base": 100}, _square_plus))
    assert out == [(i, 100 + i * i) for i in range(7)]


def test_a_failing_trial_ends_the_pool_with_its_error():
    with pytest.raises(ValueError, match="bad item -1"):
        list(run_pooled([1, -1, 2], 2, _setup, {"base": 0}, _square_plus))


def _bench(capsys, jobs: int) -> dict:
    code = main(["-q", "bench", "peg-in-hole", "--trials", "2", "--force-source", "sensor", "--seed", "4",
                 "--jobs", str(jobs), "--json"])
    assert code == 0
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


@pytest.mark.slow
def test_the_peg_bench_on_two_workers_reports_what_one_process_does(capsys):
    one, two = _bench(capsys, 1), _bench(capsys, 2)
    assert one["jobs"] == 1 and two["jobs"] == 2
    timing = {"wall_time_s", "jobs", *BENCH_CONTEXT_KEYS}  # the run's own, not its figures
    assert {k: v for k, v in one.items() if k not in timing} == {k: v for k, v in two.items() if k not in timing}
    assert [t["trial"] for t in two["per_trial"]] == [0, 1]
