"""The front's rebalancing: planned on the robots that stream, one move per interval cluster-wide."""

from __future__ import annotations

import threading
from collections import Counter

from prometheus_client import generate_latest

from lerobot_armory.entrypoints.cluster.front import MOVE_INTERVAL_S, ClusterFront, FrontOptions
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.entrypoints.cluster.metrics import FrontMetrics
from lerobot_armory.placement import Capacity
from lerobot_armory.proto import armory_pb2 as pb


class QuietReplicas:
    """Two replicas the test sets the front's view of by hand (no load calls are made)."""

    def ids(self) -> list[str]:
        return ["a", "b"]

    def load(self, replica_id, timeout):  # pragma: no cover - refresh is not called here
        raise AssertionError("not used")

    def release(self, replica_id, robot_id, timeout) -> bool:
        return True


def _front(now: list[float]) -> ClusterFront:
    front = ClusterFront(QuietReplicas(), FrontOptions(), clock=lambda: now[0])
    for state in front.state.values():
        state.view.healthy = True
        state.view.capacity = Capacity((0.05, 0.07, 0.09), 0.004)
    return front


def _robots(prefix: str, n: int) -> dict[str, RobotSpec]:
    return {f"{prefix}{k}": RobotSpec(f"{prefix}{k}", 20.0, 10, 5, 10) for k in range(n)}


def test_registrations_that_never_stream_do_not_move_anyone():
    now = [100.0]
    front = _front(now)
    front.state["a"].pending = {rid: (spec, 1e9) for rid, spec in _robots("squat", 6).items()}  # placed, not streaming
    front._rebuild(front.state["a"])
    assert len(front.state["a"].view.robots) == 6
    assert front._plan_move(now[0]) is None
    front.state["a"].reported = _robots("r", 6)  # the same load, streaming: now it is worth a move
    assert front._plan_move(now[0]) is not None


def test_at_most_one_move_per_interval_and_the_next_is_not_forgotten():
    now = [100.0]
    front = _front(now)
    front.state["a"].reported = _robots("r", 8)
    first = front._plan_move(now[0])
    assert first is not None and first.source == "a" and first.target == "b"
    front._release(first, now[0])
    front.state["a"].reported.pop(first.robot_id)
    front.state["b"].reported = {first.robot_id: RobotSpec(first.robot_id, 20.0, 10, 5, 10)}
    now[0] += MOVE_INTERVAL_S / 2
    assert front._plan_move(now[0]) is None and front._rebalance_due  # too soon: remembered
    now[0] += MOVE_INTERVAL_S
    second = front._plan_move(now[0])
    assert second is not None and second.robot_id != first.robot_id and not front._rebalance_due


def test_a_registration_that_lies_and_never_streams_leads_to_no_move():
    """Newcomers join while a registration claiming fps 20 and h_max 1 (granted by the default
    policy) sits pending and never streams: they are placed as if it were one more ordinary robot,
    so the replicas stay even and the front has no honest robot to move."""
    now = [100.0]
    front = _front(now)
    for state in front.state.values():
        state.chunk_size = 10
    front.state["a"].reported = _robots("a", 2)
    front.state["b"].reported = _robots("b", 2)
    front.state["a"].pending = {"liar": (RobotSpec("liar", 20.0, 10, 0, 1), 1e9)}
    for state in front.state.values():
        front._rebuild(state)
    for k in range(2):
        request = pb.RegisterRequest(robot_id=f"new{k}", fps=20.0, h_min=5, h_max=10, weight=1.0, tier="slow")
        rid = next(front.choices(request))
        front.state[rid].reported[f"new{k}"] = RobotSpec(f"new{k}", 20.0, 10, 5, 10)
        front._rebuild(front.state[rid])
    assert sorted(len(s.reported) for s in front.state.values()) == [3, 3]
    assert front._plan_move(now[0]) is None


def test_registrations_that_never_stream_cannot_fill_one_side_and_push_newcomers_to_the_other():
    """Three liars pending on a (the front placed them there: a had one robot streaming fewer),
    and an honest newcomer: counted with the liars, a looks fuller, but the newcomer goes to a,
    because b would then stream two robots more than a and the front would move one back."""
    now = [100.0]
    front = _front(now)
    for state in front.state.values():
        state.chunk_size = 10
    front.state["a"].reported = _robots("a", 2)
    front.state["b"].reported = _robots("b", 3)
    front.state["a"].pending = {f"liar{k}": (RobotSpec(f"liar{k}", 20.0, 10, 0, 1), 1e9) for k in range(3)}
    for state in front.state.values():
        front._rebuild(state)
    request = pb.RegisterRequest(robot_id="new", fps=20.0, h_min=5, h_max=10, weight=1.0, tier="slow")
    assert next(front.choices(request)) == "a"


def test_robots_registering_at_the_same_moment_are_spread_by_a_reservation_made_with_the_choice():
    """8 registrations placed from 8 threads at once on an empty cluster: each choice is reserved
    under the lock it was made under, so they split 4-4 (a reservation made later, as the call
    went out, let several threads choose the same replica)."""
    now = [100.0]
    front = _front(now)
    for state in front.state.values():
        state.chunk_size = 10
        state.address = f"127.0.0.1:{len(state.address) + 1}"
    barrier = threading.Barrier(8)
    chosen: list[str] = []

    def place(k: int) -> None:
        request = pb.RegisterRequest(robot_id=f"r{k}", fps=20.0, h_min=5, h_max=10, weight=1.0, tier="slow")
        barrier.wait()
        chosen.append(next(front.choices(request)))

    threads = [threading.Thread(target=place, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(Counter(chosen).values()) == [4, 4], chosen
    assert sorted(len(s.pending) for s in front.state.values()) == [4, 4]


def test_moves_are_counted_on_the_front_s_metrics():
    now = [100.0]
    front = _front(now)
    metrics = FrontMetrics(front.snapshot)
    assert "armory_front_moves_total 0.0" in generate_latest(metrics.registry).decode()
    front.state["a"].reported = _robots("r", 8)
    front._release(front._plan_move(now[0]), now[0])
    assert front.moves_made == 1
    assert "armory_front_moves_total 1.0" in generate_latest(metrics.registry).decode()
