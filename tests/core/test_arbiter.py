"""Several policies on one device: the arbiter books one policy's batch at a time, by the rule its
schedulers arbitrate with, and with one policy it is that policy's dispatcher, bit for bit."""

from __future__ import annotations

import random

import pytest

from lerobot_armory.arbiter import PolicyArbiter
from lerobot_armory.dispatch import Dispatcher
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.schedulers import EarliestDeadlineScheduler, RoundRobinScheduler
from lerobot_armory.schedulers.lookahead import LookaheadScheduler
from lerobot_armory.schedulers.rollout import RolloutScheduler
from tests.support.mirrors import mirror

FAST = LatencyProfile("fast", (20.0, 30.0, 40.0))
SLOW = LatencyProfile("slow", (200.0, 300.0, 400.0))


def robots(prefix: str, n: int, index0: int = 0, fps: float = 10.0, h: int = 5):
    out = [mirror(robot_id=f"{prefix}{k}", fps=fps, h_min=1, h_max=h) for k in range(n)]
    for k, m in enumerate(out):
        m.on_observation(index0 + k, 0.0, 0.0)
    return out


def _replay(make, seed: int, arbiter: bool) -> list[tuple[float, tuple[str, ...]]]:
    """A random fleet's decisions over 3 s, through a dispatcher or a one-policy arbiter."""
    rng = random.Random(seed)
    fleet = robots("r", 6)
    dispatcher = Dispatcher(make())
    arb = PolicyArbiter({"only": dispatcher}) if arbiter else None
    t, out = 0.0, []
    while t < 3.0:
        for m in fleet:
            if rng.random() < 0.5:
                m.on_observation(m.obs_index + rng.randint(1, 3), t, t)  # capped by what was sent
        if arb is not None:
            got = arb.plan({"only": fleet}, t)
            plan = None if got is None else got[1]
        else:
            plan = dispatcher.plan(fleet, t)
        if plan is None or not plan.requests:
            t += 0.05
            continue
        out.append((round(plan.t_done, 9), tuple(plan.robot_ids)))
        dispatcher.complete(plan, plan.t_done)
        t = plan.t_done
    return out


@pytest.mark.parametrize(
    "make",
    [
        lambda: RoundRobinScheduler(FAST, 3),
        lambda: EarliestDeadlineScheduler(FAST, 3),
        lambda: LookaheadScheduler(FAST, 3),
        lambda: RolloutScheduler(FAST, 3),
    ],
    ids=["rr", "edf", "lookahead", "rollout"],
)
def test_one_policy_plans_exactly_as_its_dispatcher(make):
    for seed in range(3):
        alone = _replay(make, seed, arbiter=False)
        assert len(alone) > 10
        assert _replay(make, seed, arbiter=True) == alone


def test_a_batch_holds_robots_of_one_policy_booked_on_that_policys_dispatcher():
    a, b = robots("a", 2), robots("b", 2)
    arb = PolicyArbiter({"A": Dispatcher(EarliestDeadlineScheduler(FAST, 3)), "B": Dispatcher(EarliestDeadlineScheduler(SLOW, 3))})
    name, plan = arb.plan({"A": a, "B": b}, 0.0)
    assert {robot_id[0] for robot_id in plan.robot_ids} == {name.lower()}
    served = a if name == "A" else b
    assert all(m.queue for m in served) and all(not m.queue for m in (b if name == "A" else a))
    # Its predicted completion uses its own policy's d_infer.
    assert plan.t_done == pytest.approx((FAST if name == "A" else SLOW).latency_ms[len(served) - 1] / 1000.0)
    arb.complete(name, plan, plan.t_done)
    other, plan2 = arb.plan({"A": a, "B": b}, plan.t_done)
    assert other != name and len(plan2.requests) == 2


def test_round_robin_rotates_the_policies_with_work():
    fleets = {n: robots(n, 1) for n in "XYZ"}
    arb = PolicyArbiter({n: Dispatcher(RoundRobinScheduler(FAST, 2)) for n in "XYZ"})
    order = []
    for step in range(6):
        t = float(step)
        name, plan = arb.plan(fleets, t)
        order.append(name)
        arb.complete(name, plan, t + 0.01)
        for m in fleets[name]:
            m.on_observation(m.obs_index + 2, t + 0.5, t + 0.5)  # executed 2 of the chunk: useful again
    assert order == ["X", "Y", "Z", "X", "Y", "Z"]
    # A policy with nothing useful is skipped.
    fleets["Y"][0].on_dispatch(10.0)
    assert [arb.plan(fleets, 10.0)[0], arb.plan(fleets, 10.0)[0]] == ["X", "Z"]


def test_edf_serves_the_policy_whose_robot_is_due_first():
    early = robots("e", 1, index0=0)  # its chunk runs dry first
    late = robots("l", 1, index0=0, h=5)
    # "late" holds a chunk, so its deadline is later; "early" has none.
    chunk = late[0].on_dispatch(0.0)
    late[0].on_complete(chunk, 0.02)
    late[0].on_observation(1, 0.1, 0.1)
    assert early[0].deadline() < late[0].deadline()
    arb = PolicyArbiter({"late": Dispatcher(EarliestDeadlineScheduler(FAST, 2)), "early": Dispatcher(EarliestDeadlineScheduler(SLOW, 2))})
    name, _ = arb.plan({"late": late, "early": early}, 0.1)
    assert name == "early"


class _Scored(EarliestDeadlineScheduler):
    """EDF's batch, scored by a plugin's own measure (here: minus d_infer of the batch)."""

    arbitration = "score"

    def select(self, robots, now):
        batch = super().select(robots, now)
        self.last_score = -self.d_infer[len(batch) - 1]
        return batch


def test_a_scoring_scheduler_gives_the_device_to_the_highest_score():
    arb = PolicyArbiter({"slow": Dispatcher(_Scored(SLOW, 3)), "fast": Dispatcher(_Scored(FAST, 3))})
    name, plan = arb.plan({"slow": robots("s", 2), "fast": robots("f", 2)}, 0.0)
    assert name == "fast" and plan.requests
    # Every builtin scheduler but RR arbitrates by deadline (Lookahead's score favours cheap policies).
    assert [s.arbitration for s in (LookaheadScheduler(FAST, 2), RolloutScheduler(FAST, 2), EarliestDeadlineScheduler(FAST, 2))] == ["deadline"] * 3


class _Seeing(EarliestDeadlineScheduler):
    """EDF that notes the peers it was shown at each decision."""

    def __init__(self, *args):
        super().__init__(*args)
        self.seen = []

    def select(self, robots, now):
        self.seen.append(self.peers)
        return super().select(robots, now)


def test_each_scheduler_sees_the_other_policies_for_one_decision_only():
    a, b = robots("a", 2), robots("b", 3)
    sa, sb = _Seeing(FAST, 3), _Seeing(SLOW, 2)
    arb = PolicyArbiter({"A": Dispatcher(sa), "B": Dispatcher(sb)})
    name, plan = arb.plan({"A": a, "B": b}, 0.0)
    deciding, other = (sa, sb) if name == "A" else (sb, sa)
    (peers,) = deciding.seen
    (peer,) = peers
    assert list(peer.robots) == (b if name == "A" else a)
    assert list(peer.d_infer) == list(other.d_infer) and peer.max_batch_size == other.max_batch_size
    assert sa.peers == () and sb.peers == ()  # cleared once the batch is booked
    # A policy with no robots is no peer; with one policy nothing is ever shown.
    assert arb.plan({"A": robots("x", 2), "B": []}, 1.0)[0] == "A"
    assert sa.seen[-1] == ()
    alone = _Seeing(FAST, 3)
    PolicyArbiter({"only": Dispatcher(alone)}).plan({"only": robots("c", 2)}, 0.0)
    assert alone.seen == [()]


def test_schedulers_that_arbitrate_differently_cannot_share_a_device():
    with pytest.raises(ValueError, match="arbitrate alike"):
        PolicyArbiter({"a": Dispatcher(RoundRobinScheduler(FAST, 2)), "b": Dispatcher(EarliestDeadlineScheduler(FAST, 2))})
    with pytest.raises(ValueError, match="at least one"):
        PolicyArbiter({})


def test_no_useful_robot_anywhere_means_no_plan():
    idle = [mirror(robot_id="idle")]
    arb = PolicyArbiter({"a": Dispatcher(EarliestDeadlineScheduler(FAST, 2)), "b": Dispatcher(EarliestDeadlineScheduler(FAST, 2))})
    assert arb.plan({"a": idle, "b": []}, 0.0) is None
    assert arb.plan({}, 0.0) is None and not arb.has_work({"a": idle})
