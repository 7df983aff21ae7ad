"""Placement (pure): the load model and the four policies, and rebalancing."""

from __future__ import annotations

import math
import random

import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import load_profile
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.placement import (
    PLACEMENTS,
    Capacity,
    NoReplica,
    ReplicaView,
    demand,
    make_placement,
    place_all,
    balanced_choices,
    rebalance,
    with_unverified,
)

L40S = Capacity(tuple(load_profile("l40s-pi05").table_s(3)), 0.00375)
H100 = Capacity(tuple(load_profile("h100-pi05").table_s(3)), 0.00375)


def fast(k: int, weight: float = 3.0) -> RobotSpec:
    return RobotSpec(f"fast{k:02d}", 20.0, 10, 1, 6, weight, "fast")


def slow(k: int) -> RobotSpec:
    return RobotSpec(f"slow{k:02d}", 20.0, 10, 1, 10, 1.0, "slow")


def replicas(n: int, capacity: Capacity = L40S, **kwargs) -> list[ReplicaView]:
    return [ReplicaView(f"gpu{k}", capacity, **kwargs) for k in range(n)]


def fast_per_replica(views: list[ReplicaView]) -> list[int]:
    return [sum(s.tier == "fast" for s in r.robots.values()) for r in views]


def test_demand_grows_as_the_horizon_shrinks_and_is_capped_at_one_serve_per_tick():
    values = [demand(RobotSpec("r", 20.0, 10, 1, h, 1.0, "slow"), L40S) for h in (10, 8, 6, 4)]
    assert values == sorted(values) and len(set(values)) == 4
    # period = h_max / fps - round trip; cost = d_infer(b) / b at the cap
    assert values[0] == pytest.approx((0.1424 / 3) / (10 / 20 - (0.1424 + 2 * 0.00375)))
    # A horizon shorter than the round trip cannot be met at any rate: served every tick at most.
    tiny = demand(RobotSpec("r", 20.0, 10, 1, 1, 1.0, "slow"), L40S)
    assert tiny == pytest.approx((0.1424 / 3) * 20)
    # h_min bounds the rate too (the mirror never serves a robot more often).
    gated = demand(RobotSpec("r", 20.0, 10, 4, 4, 1.0, "slow"), L40S)
    assert gated == pytest.approx((0.1424 / 3) / (4 / 20))
    # A faster GPU: less demand for the same robot.
    assert demand(fast(0), H100) < demand(fast(0), L40S)


def test_capacity_rejects_impossible_tables():
    with pytest.raises(ConfigError):
        Capacity((), 0.0)
    with pytest.raises(ConfigError):
        Capacity((0.1, 0.0), 0.0)
    with pytest.raises(ConfigError):
        Capacity((0.1,), -1.0)


@pytest.mark.parametrize("seed", range(12))
def test_mirror_aware_spreads_fast_robots_whatever_the_join_order(seed):
    specs = [fast(k) for k in range(4)] + [slow(k) for k in range(12)]
    random.Random(seed).shuffle(specs)
    views = replicas(4)
    place_all(specs, views, make_placement("mirror_aware", seed))
    assert fast_per_replica(views) == [1, 1, 1, 1]
    loads = [r.utilization() for r in views]
    assert max(loads) - min(loads) <= demand(fast(0), L40S) + 1e-9  # balanced to within one robot


def test_counting_policies_cluster_fast_robots_that_join_in_step_mirror_aware_does_not():
    # Slow and fast robots joining alternately: dealing by count puts every fast robot on one GPU.
    specs = [spec for k in range(4) for spec in (slow(k), fast(k))]
    for name in ("round_robin", "least_loaded"):
        views = replicas(2)
        place_all(specs, views, make_placement(name))
        assert fast_per_replica(views) == [0, 4], name
    clustered = 0
    for seed in range(20):
        views = replicas(2)
        place_all(specs, views, make_placement("random", seed))
        clustered += max(fast_per_replica(views)) >= 3
    assert clustered > 0  # random does pile fast robots up for some seeds
    views = replicas(2)
    place_all(specs, views, make_placement("mirror_aware"))
    assert fast_per_replica(views) == [2, 2]


def test_mirror_aware_gives_a_slower_replica_fewer_robots():
    views = [ReplicaView("a-h100", H100), ReplicaView("b-l40s", L40S)]
    place_all([slow(k) for k in range(12)], views, make_placement("mirror_aware"))
    on = {r.replica_id: len(r.robots) for r in views}
    assert on["a-h100"] > on["b-l40s"] >= 1
    # Each added robot went where the predicted utilization stays lowest: the two end close.
    assert abs(views[0].utilization() - views[1].utilization()) <= demand(slow(0), L40S) + 1e-9
    # least_loaded ignores the GPUs' speeds: equal counts, the slow GPU far fuller.
    views2 = [ReplicaView("a-h100", H100), ReplicaView("b-l40s", L40S)]
    place_all([slow(k) for k in range(12)], views2, make_placement("least_loaded"))
    assert [len(r.robots) for r in views2] == [6, 6]
    assert max(r.utilization() for r in views2) > max(r.utilization() for r in views)


@pytest.mark.parametrize("name", list(PLACEMENTS))
def test_every_policy_skips_unhealthy_and_full_replicas_and_raises_when_none_is_open(name):
    views = [
        ReplicaView("gpu0", L40S, healthy=False),
        ReplicaView("gpu1", L40S, robots={"x": slow(99)}, max_robots=1),
        ReplicaView("gpu2", L40S, max_robots=2),
    ]
    policy = make_placement(name, 0)
    where = place_all([slow(0), fast(0)], views, policy)
    assert set(where.values()) == {"gpu2"}
    with pytest.raises(NoReplica):
        policy.choose(slow(1), views)


def test_make_placement_names_the_known_ones():
    with pytest.raises(ConfigError, match="placement.*mirror_aware"):
        make_placement("nope")


def test_round_robin_deals_in_replica_order():
    views = replicas(3)
    where = place_all([slow(k) for k in range(7)], views, make_placement("round_robin"))
    assert [where[slow(k).robot_id] for k in range(7)] == ["gpu0", "gpu1", "gpu2", "gpu0", "gpu1", "gpu2", "gpu0"]


def test_least_loaded_picks_the_fewest_robots_whatever_their_demand():
    views = [
        ReplicaView("gpu0", L40S, robots={"a": slow(90)}),
        ReplicaView("gpu1", L40S, robots={"b": fast(90), "c": fast(91)}),
    ]
    assert make_placement("least_loaded").choose(fast(0), views) == "gpu0"
    views[0].robots.update({"d": slow(91), "e": slow(92)})  # 3 light robots vs 2 heavy ones
    assert make_placement("least_loaded").choose(fast(0), views) == "gpu1"
    assert make_placement("mirror_aware").choose(fast(0), views) == "gpu0"  # lower utilization


def test_random_uses_every_replica_and_is_reproducible_by_seed():
    specs = [slow(k) for k in range(40)]
    first = place_all(specs, replicas(4), make_placement("random", 7))
    again = place_all(specs, replicas(4), make_placement("random", 7))
    other = place_all(specs, replicas(4), make_placement("random", 8))
    assert first == again
    assert first != other
    assert set(first.values()) == {"gpu0", "gpu1", "gpu2", "gpu3"}


@pytest.mark.parametrize("name", list(PLACEMENTS))
def test_place_all_is_deterministic_for_a_seed(name):
    specs = [fast(k) for k in range(5)] + [slow(k) for k in range(15)]
    random.Random(3).shuffle(specs)
    a = place_all(specs, replicas(4), make_placement(name, 3))
    b = place_all(specs, replicas(4), make_placement(name, 3))
    assert a == b and len(a) == 20


def test_rebalance_moves_a_robot_off_the_busiest_replica():
    views = [
        ReplicaView("gpu0", L40S, robots={s.robot_id: s for s in [fast(0), fast(1), slow(0)]}),
        ReplicaView("gpu1", L40S),
        ReplicaView("gpu2", L40S, robots={"s1": slow(1), "s2": slow(2)}),
    ]
    before = max(r.utilization() for r in views)
    move = rebalance(views)
    assert move is not None and move.source == "gpu0" and move.target == "gpu1"
    by_id = {r.replica_id: r for r in views}
    spec = by_id[move.source].robots.pop(move.robot_id)
    by_id[move.target].robots[move.robot_id] = spec
    after = max(r.utilization() for r in views)
    assert after < before - 0.1
    assert spec.tier == "fast"  # moving a heavy robot is what lowers the peak most


def test_rebalance_proposes_nothing_when_balanced_or_alone():
    views = [ReplicaView(f"gpu{k}", L40S, robots={f"s{k}": slow(k), f"f{k}": fast(k)}) for k in range(3)]
    assert rebalance(views) is None
    assert rebalance(views[:1]) is None
    # An unhealthy replica is never a target.
    lopsided = [
        ReplicaView("gpu0", L40S, robots={"a": fast(0), "b": fast(1)}),
        ReplicaView("gpu1", L40S, healthy=False),
    ]
    assert rebalance(lopsided) is None


def test_utilization_counts_the_extra_robot():
    view = ReplicaView("gpu0", L40S, robots={"a": slow(0)})
    assert view.utilization(fast(0)) == pytest.approx(view.utilization() + demand(fast(0), L40S))
    assert math.isclose(ReplicaView("x", L40S).utilization(), 0.0)


def test_a_registration_that_has_not_streamed_counts_as_one_more_robot_like_the_newcomer():
    liar = RobotSpec("liar", 1000.0, 10, 0, 1, 1.0, "slow")  # claims a chunk every millisecond
    view = ReplicaView("gpu0", H100, robots={"s0": slow(0), "liar": liar}, max_robots=3)
    newcomer = slow(1)
    placed = with_unverified(view, {"s0": slow(0)}, ["liar"], newcomer)
    assert placed.robots["s0"] == slow(0)
    assert placed.robots["liar"] == RobotSpec("liar", 20.0, 10, 1, 10, 1.0, "slow")  # the newcomer's claim, not its own
    assert placed.utilization() == pytest.approx(2 * demand(newcomer, H100))
    assert placed.max_robots == 3 and len(placed.robots) == 2 and placed.open
    assert view.robots["liar"] == liar  # the front's own view is left as it was
    # The newcomer's own earlier registration is not counted twice.
    assert "slow01" not in with_unverified(view, {}, ["slow01"], newcomer).robots


def test_a_pending_liar_does_not_steer_honest_newcomers_onto_one_replica():
    """Two replicas with two streaming robots each; a registration that claims fps 1000, h_max 1
    and never streams is pending on gpu0. Believed, it sends both newcomers to gpu1 (2 vs 4, which
    a later rebalance evens out by moving an honest robot); as one more ordinary robot, it does not."""
    liar = RobotSpec("liar", 1000.0, 10, 0, 1, 1.0, "slow")
    streaming = [{"a": slow(0), "b": slow(1)}, {"c": slow(2), "d": slow(3)}]
    pending = [["liar"], []]
    policy = make_placement("mirror_aware")
    believed = [dict(s) for s in streaming]
    for k, newcomer in enumerate([slow(10), slow(11)]):
        views = [ReplicaView(f"gpu{r}", H100, robots={**believed[r], **({"liar": liar} if pending[r] else {})}) for r in range(2)]
        believed[int(policy.choose(newcomer, views)[-1])][newcomer.robot_id] = newcomer
    assert [len(r) for r in believed] == [2, 4]
    assert rebalance([ReplicaView(f"gpu{r}", H100, robots=believed[r]) for r in range(2)]) is not None
    for k, newcomer in enumerate([slow(10), slow(11)]):
        views = [
            with_unverified(ReplicaView(f"gpu{r}", H100), streaming[r], pending[r], newcomer) for r in range(2)
        ]
        streaming[int(policy.choose(newcomer, views)[-1])][newcomer.robot_id] = newcomer
    assert [len(r) for r in streaming] == [3, 3]
    assert rebalance([ReplicaView(f"gpu{r}", H100, robots=streaming[r]) for r in range(2)]) is None


def test_placement_never_makes_the_imbalance_a_move_would_undo():
    """Liars placed on gpu0 (registrations that never stream) balance the count that includes them
    against gpu1's one extra streaming robot; a newcomer counted that way would go to gpu1 (2 vs 4
    streaming, and a move). balanced_choices leaves gpu0 only."""
    streaming = [{"a": slow(0), "b": slow(1)}, {"c": slow(2), "d": slow(3), "e": slow(4)}]
    pending = [["liar0", "liar1", "liar2"], []]
    newcomer = slow(10)
    placed = [with_unverified(ReplicaView(f"gpu{r}", H100), streaming[r], pending[r], newcomer) for r in range(2)]
    assert make_placement("mirror_aware").choose(newcomer, placed) == "gpu1"
    views = [ReplicaView(f"gpu{r}", H100, robots=streaming[r]) for r in range(2)]
    assert balanced_choices(newcomer, views) == {"gpu0"}
    # Balanced robots: either replica keeps them so; already unbalanced, or unhealthy: no restriction.
    even = [ReplicaView(f"gpu{r}", H100, robots={f"s{r}{k}": slow(10 * r + k) for k in range(2)}) for r in range(2)]
    assert balanced_choices(newcomer, even) == {"gpu0", "gpu1"}
    lopsided = [ReplicaView("gpu0", H100, robots={f"s{k}": slow(k) for k in range(5)}), ReplicaView("gpu1", H100)]
    assert balanced_choices(newcomer, lopsided) == {"gpu0", "gpu1"}
    views[1].healthy = False
    assert balanced_choices(newcomer, views) == {"gpu0"}


def test_robots_registering_together_still_spread():
    """A failed replica's 6 robots re-register before any of them is reported streaming: each
    earlier one counts as pending, so they spread over the two survivors."""
    streaming = [{"a": slow(0)}, {"b": slow(1)}]
    pending: list[list[str]] = [[], []]
    policy = make_placement("mirror_aware")
    for k in range(6):
        newcomer = slow(20 + k)
        placed = [with_unverified(ReplicaView(f"gpu{r}", H100), streaming[r], pending[r], newcomer) for r in range(2)]
        keep = balanced_choices(newcomer, [ReplicaView(f"gpu{r}", H100, robots=streaming[r]) for r in range(2)])
        chosen = policy.choose(newcomer, [v for v in placed if v.replica_id in keep])
        pending[int(chosen[-1])].append(newcomer.robot_id)
    assert [len(p) for p in pending] == [3, 3]
