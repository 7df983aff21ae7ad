"""The Lagrangian device-pricing upper bound (armory_research.bound)."""

from __future__ import annotations

import pytest

from lerobot_armory.inference_latency import load_profile
from lerobot_armory.schedulers import make_scheduler_config
from armory_research.bound import device_time, lagrangian_bound, robot_value
from armory_research.optimal import Episode, episode_for, play, solve

PROFILE = load_profile("l40s-pi05")


def solved(preset: str, mix: str, robots: int, horizon: float) -> tuple[Episode, float]:
    """An episode small enough for the exact search, and its optimum (which must be exact)."""
    ep = episode_for(preset, mix, robots, horizon)
    exact = solve(ep, time_limit_s=60)
    assert exact.exact
    return ep, exact.value


def test_one_robot_bound_by_hand():
    # A lone libero robot (see test_frontier's hand case): its first chunk can land at 80.5 ms
    # at best, so ticks 0 and 1 starve whatever the price; at price 0 chunks are free and it never
    # starves again: 18 of 20 ticks -> 0.9 robot-s, which is also the exact optimum.
    ep = episode_for("libero", "one-fast", 1, 1.0)
    assert robot_value(ep, 0, 0.0) == pytest.approx(0.9)
    b = lagrangian_bound(ep)
    assert b.upper_bound == pytest.approx(0.9, abs=1e-6)
    # Any positive price only lowers V_j: the dual minimum is at (or next to) 0 here.
    assert robot_value(ep, 0, 1.0) < 0.9


@pytest.mark.parametrize(
    "preset,mix,robots,horizon",
    [("libero", "one-fast", 3, 2.0), ("libero", "all-fast", 3, 1.0), ("piper", "half-fast", 4, 1.0)],
)
def test_bound_is_above_the_exact_optimum(preset, mix, robots, horizon):
    ep, optimum = solved(preset, mix, robots, horizon)
    assert lagrangian_bound(ep).upper_bound >= optimum - 1e-9


def test_bound_is_above_every_scheduler_and_below_the_ceiling_when_overloaded():
    # Six fast libero robots overload the device: the bound must say so (well below every tick
    # executed) while staying above what every scheduler achieves.
    ep = episode_for("libero", "all-fast", 6, 3.0)
    b = lagrangian_bound(ep)
    assert b.upper_bound < 0.85 * ep.max_weighted_s()
    assert b.price > 0
    for name in ("rr", "edf", "lookahead", "rollout"):
        value = play(ep, make_scheduler_config(name).build(PROFILE, ep.max_batch_size)).weighted_executed_s
        assert value <= b.upper_bound + 1e-9
    # Tighter than the branch-and-bound's own bound after a short search.
    cut = solve(ep, node_limit=2000)
    assert not cut.exact and b.upper_bound < cut.upper_bound


def test_device_time_and_warmup_guard():
    ep = episode_for("libero", "one-fast", 2, 1.0)
    assert device_time(ep) == pytest.approx(1.0 - 2 * 0.00375)
    with pytest.raises(ValueError, match="warmup"):
        lagrangian_bound(episode_for("libero", "one-fast", 2, 1.0, warmup_s=0.5))


# ---- per-slot device prices (the time-priced bound) ---------------------------------------------


def test_cheapest_window_matches_a_fine_scan():
    # The window integral is piecewise linear in its start: the breakpoints must find the same
    # minimum as a dense scan (and never a smaller one).
    import numpy as np

    from armory_research.bound import DevicePrices

    rng = np.random.default_rng(0)
    prices = DevicePrices(rng.uniform(0, 3, size=200), 0.005)
    for _ in range(50):
        lo = float(rng.uniform(0, 0.8))
        hi = lo + float(rng.uniform(0, 0.05))
        d = float(rng.uniform(0.05, 0.2))
        cost, s = prices.cheapest(lo, hi, d)
        assert lo - 1e-12 <= s <= hi + 1e-12
        assert cost == pytest.approx(prices.integral(s + d) - prices.integral(s))
        scan = min(prices.integral(x + d) - prices.integral(x) for x in np.linspace(lo, hi, 400))
        assert cost <= scan + 1e-9


def test_plan_load_adds_up_to_the_chunks_device_shares():
    from armory_research.bound import DevicePrices, robot_plan

    ep = episode_for("libero", "all-fast", 4, 2.0)
    prices = DevicePrices.flat(1.0, ep)
    value, plan = robot_plan(ep, 0, prices)
    assert value == pytest.approx(robot_value(ep, 0, 1.0))
    assert plan, "at price 1 a chunk still pays for itself"
    fine = DevicePrices([0.0] * 400, 0.005)
    assert float(fine.load(plan, 3).sum()) * 0.005 == pytest.approx(3 * sum(d / b for _, d, b in plan))
    # The plan's chunks run one after the other (the robot waits for its previous batch).
    for (s1, d1, _), (s2, _, _) in zip(plan, plan[1:]):
        assert s2 >= s1 + d1 - 0.005 - 1e-9


@pytest.mark.parametrize(
    "preset,mix,robots,horizon",
    [("libero", "all-fast", 4, 1.0), ("libero", "half-fast", 4, 1.0), ("piper", "all-fast", 4, 1.0)],
)
def test_time_priced_bound_is_between_the_optimum_and_the_flat_bound(preset, mix, robots, horizon):
    from armory_research.bound import time_priced_bound

    ep, optimum = solved(preset, mix, robots, horizon)
    flat = lagrangian_bound(ep)
    tp = time_priced_bound(ep, optimum, flat, iterations=15)
    assert optimum - 1e-9 <= tp.upper_bound <= flat.upper_bound + 1e-12


def test_time_priced_bound_is_tighter_when_overloaded():
    from armory_research.bound import time_priced_bound

    # Six fast libero robots: one flat price lets every robot dispatch the instant its
    # observation lands; per-slot prices charge those contested instants.
    ep = episode_for("libero", "all-fast", 6, 3.0)
    flat = lagrangian_bound(ep)
    edf = play(ep, make_scheduler_config("edf").build(PROFILE, ep.max_batch_size)).weighted_executed_s
    tp = time_priced_bound(ep, edf, flat, iterations=25)
    assert tp.upper_bound < flat.upper_bound - 0.1
    assert tp.upper_bound >= edf
