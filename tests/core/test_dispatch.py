"""The dispatch step: plan / complete / cancel, the batch contract inside, failure isolation, and
that every driver of the mirrors goes through it (the transition's bookkeeping is written once)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from lerobot_armory.dispatch import Dispatcher
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.transition import Chunk
from lerobot_armory.schedulers import EarliestDeadlineScheduler, RoundRobinScheduler
from lerobot_armory.schedulers.base import Scheduler
from tests.support.mirrors import mirror

PROFILE = LatencyProfile("test", (100.0, 150.0, 200.0))  # d_infer 0.1 / 0.15 / 0.2 s
ROOT = Path(__file__).resolve().parents[2]


def fleet(n: int = 3):
    robots = [mirror(robot_id=f"r{k}", fps=10.0, h_min=1, h_max=5) for k in range(n)]
    for k, m in enumerate(robots):
        m.on_observation(10 * k, 0.0, 0.0)
    return robots


def test_no_useful_robot_means_no_plan():
    robots = [mirror(robot_id="idle")]  # no observation yet
    assert Dispatcher(EarliestDeadlineScheduler(PROFILE, 3)).plan(robots, 0.0) is None


def test_plan_books_each_request_on_its_mirror_and_names_it_by_robot_id():
    robots = fleet(3)
    plan = Dispatcher(RoundRobinScheduler(PROFILE, 2)).plan(robots, 1.0)
    assert plan is not None and plan.robot_ids == ["r0", "r1"] and plan.size == 2
    assert plan.t_done == pytest.approx(1.15)  # d_infer(2)
    for req, m in zip(plan.requests, robots, strict=False):
        assert req.mirror is m and req.chunk in m.queue
        assert (req.chunk.i_start, req.chunk.h) == (m.obs_index, 5)
        assert req.chunk.t_arrival == pytest.approx(1.15)  # zero one-way delay in these mirrors
        assert (req.chunk.capture_robot, req.chunk.obs_recv) == (0.0, 0.0)
        assert m.last_served_index == m.obs_index and not m.is_useful()
        assert req.previous_last_served is None
    assert robots[2].queue == [] and robots[2].is_useful()
    assert plan.decision_s >= 0.0 and plan.decision_cpu_s >= 0.0


def test_complete_replaces_the_prediction_and_cancel_undoes_the_booking():
    robots = fleet(2)
    d = Dispatcher(EarliestDeadlineScheduler(PROFILE, 2))
    plan = d.plan(robots, 0.0)
    d.complete(plan, 0.4)  # slower than d_infer(2) = 0.15
    assert plan.t_done == 0.4
    assert all(r.chunk.t_arrival == 0.4 and r.chunk.t_sent == 0.4 for r in plan.requests)
    assert robots[0].on_report(plan.requests[0].chunk.chunk_id, 0.45) is True  # awaited, one exchange

    robots = fleet(2)
    plan = d.plan(robots, 0.0)
    d.cancel(plan)
    assert all(m.queue == [] and m.is_useful() and m.last_served_index is None for m in robots)
    assert robots[0].on_report(plan.requests[0].chunk.chunk_id, 0.45) is None  # no longer awaited


class _Broken(Scheduler):
    """Returns a robot whose request is not useful: a contract violation."""

    def select(self, robots, now):
        return [r for r in robots if not r.is_useful()][:1] or list(robots)[:1] * 2


def test_the_batch_contract_is_checked_inside():
    robots = fleet(2)
    robots[0].on_dispatch(0.0)  # r0 not useful any more
    with pytest.raises(RuntimeError, match="not useful"):
        Dispatcher(_Broken(PROFILE, 2)).plan(robots, 0.0)


def test_isolated_failures_fall_back_to_the_first_useful_robots():
    robots = fleet(3)
    robots[0].on_dispatch(0.0)
    plan = Dispatcher(_Broken(PROFILE, 2), isolate_failures=True).plan(robots, 0.0)
    assert plan.fell_back and plan.robot_ids == ["r1", "r2"] and plan.quarantined == []


def test_a_robot_whose_state_cannot_be_evaluated_is_quarantined_and_the_rest_served():
    robots = fleet(3)
    robots[1].queue.append(Chunk(99, 10, 5, math.nan))  # what a bug or a poisoned time would leave behind
    with pytest.raises(ValueError):
        Dispatcher(EarliestDeadlineScheduler(PROFILE, 3)).plan(robots, 0.0)
    plan = Dispatcher(EarliestDeadlineScheduler(PROFILE, 3), isolate_failures=True).plan(robots, 0.0)
    assert [rid for rid, _ in plan.quarantined] == ["r1"] and "ValueError" in plan.quarantined[0][1]
    assert sorted(plan.robot_ids) == ["r0", "r2"] and not plan.fell_back


def test_only_the_dispatch_step_books_chunks_on_mirrors():
    """The live loop, the simulator and the study never call the mirror's dispatch events
    themselves, nor write a chunk's arrival: the dispatch step and the mirror do."""
    offenders = []
    sources = [*ROOT.glob("lerobot_armory/**/*.py"), *ROOT.glob("research/**/*.py")]
    for path in sources:
        rel = path.relative_to(ROOT).as_posix()
        if rel in ("lerobot_armory/dispatch.py", "lerobot_armory/mirror.py"):
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(r"\.on_(dispatch|complete|cancel)\(|\.t_arrival\s*=(?!=)", line):
                offenders.append(f"{rel}:{n}: {line.strip()}")
    assert offenders == []
    for driver in ("lerobot_armory/serving/loop.py", "lerobot_armory/sim/simulator.py", "research/armory_research/optimal.py"):
        assert "Dispatcher(" in (ROOT / driver).read_text(), driver
