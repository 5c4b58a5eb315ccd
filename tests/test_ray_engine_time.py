"""Where a Ray sweep's engine-time goes: the driver's clock of each engine
(`placement.EngineClock`) and the scaling benchmark's split of the shortfall from perfect
scaling (benchmarks/ray_scaling.py), on given times (the live accounting is tested on a Ray
cluster in test_sweep_ray.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from vabench.sweep.placement import EngineClock

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import ray_scaling


def test_an_engines_clock_splits_its_life_into_start_up_working_and_waiting():
    clock = EngineClock(asked_at=100.0)
    clock.started_at = 112.0  # 12 s of start-up
    clock.work_began(115.0)
    clock.work_began(118.0)  # a second chunk while the first runs: one working span
    clock.work_ended(130.0)
    clock.work_began(140.0)
    # still working at 150: counted up to now
    assert clock.figures(150.0) == {
        "start_up_s": 12.0,
        "working_s": 25.0,
        "waiting_s": 13.0,
        "life_s": 50.0,
    }
    clock.end(160.0)
    clock.end(999.0)  # a second end changes nothing
    assert clock.figures(999.0) == {
        "start_up_s": 12.0,
        "working_s": 35.0,
        "waiting_s": 13.0,
        "life_s": 60.0,
    }


def test_a_span_that_began_at_zero_counts():
    clock = EngineClock(asked_at=0.0)
    clock.started_at = 0.0
    clock.work_began(0.0)
    assert clock.figures(10.0)["working_s"] == 10.0


def test_an_engine_that_never_started_spent_its_life_starting():
    clock = EngineClock(asked_at=0.0)
    clock.end(30.0)
    assert clock.figures(99.0) == {
        "start_up_s": 30.0,
        "working_s": 0.0,
        "waiting_s": 0.0,
        "life_s": 30.0,
    }


def engine(start_up: float, working: float, waiting: float) -> dict:
    return {"start_up_s": start_up, "working_s": working, "waiting_s": waiting}


def test_the_lost_time_parts_sum_to_the_shortfall_from_perfect_scaling():
    episodes = 280
    one = {"engines": 1, "wall_s": 100.0, "episodes_per_s": episodes / 100.0}
    one["engine_time"] = ray_scaling.engine_time([engine(10, 85, 3)], 1, 100.0)
    four = {"engines": 4, "wall_s": 30.0, "episodes_per_s": episodes / 30.0}
    four["engine_time"] = ray_scaling.engine_time(
        [engine(11, 14, 4), engine(10, 18, 1), engine(12, 10, 7), engine(10, 19, 0.5)], 4, 30.0
    )
    assert four["engine_time"]["total_s"] == 120.0
    assert four["engine_time"]["other_s"] == pytest.approx(120.0 - 116.5)
    ratio = four["episodes_per_s"] / (4 * one["episodes_per_s"])
    lost = ray_scaling.lost_time(four, one)
    assert sum(lost.values()) == pytest.approx(1 - ratio)
    assert lost["start_up_s"] == pytest.approx((43 - 10) / 120)
    assert lost["working_s"] == pytest.approx((61 - 85) / 120)  # fewer working seconds here
    assert lost["waiting_s"] == pytest.approx((12.5 - 3) / 120)
    assert ray_scaling.lost_time(one, one) == dict.fromkeys(ray_scaling.PARTS, 0.0)


def test_the_dealing_ab_hides_and_sets_this_machines_paces_and_puts_the_file_back():
    """`ray_scaling.py --dealing budgets,measured`: the driver reads this machine's paces when
    a sweep starts; the benchmark shows it none (budgets), then the budgets run's own, and
    leaves the user's pace file byte for byte as it found it."""
    import json
    import socket
    from dataclasses import asdict

    from vabench.check.pace import KindPace, machine_paces, pace_file

    mine = KindPace("embedded:reference_servo", "/runs/a", 4, 40, 8.0, 1e6, "all", 1.0)
    path = pace_file()  # each test's own (conftest)
    with ray_scaling.paces_as({}):
        assert machine_paces() == {}
    assert not path.exists()  # none before, none after

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        json.dumps({socket.gethostname(): {mine.kind: asdict(mine)}, "other-host": {"k": {}}})
    )
    before = path.read_bytes()
    with ray_scaling.paces_as({}):
        assert machine_paces() == {}
        assert "other-host" in json.loads(path.read_text())  # another machine's stay
    measured = KindPace(mine.kind, "/runs/b", 4, 40, 4.0, 1e6, "all", 2.0, {"lift_pot": 3.5})
    with ray_scaling.paces_as({measured.kind: asdict(measured)}):
        assert machine_paces() == {measured.kind: measured}
    assert path.read_bytes() == before
