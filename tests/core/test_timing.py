"""Dispatch timing (``--scheduler.wait_ms``): the rule, the dispatcher's cap, every driver honours a wait."""

from __future__ import annotations

import math

import pytest

from lerobot_armory.network_delay import LogNormalDelay
from lerobot_armory.dispatch import Dispatcher
from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile, load_profile
from lerobot_armory.delay import DelayEstimator
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.schedulers import EarliestDeadlineScheduler, make_scheduler_config
from lerobot_armory.schedulers.dispatch_timing import hold_until
from lerobot_armory.sim import FleetSimulator, fleet_specs, get_preset

# libero's timing: 20 fps, one-way 3.75 ms, d_infer 73 / 109.8 / 142.4 ms.
D = (0.073, 0.1098, 0.1424)
ONE_WAY = 0.00375


def robot(name: str, tick: int, h_max: int = 6) -> RobotMirror:
    """A 20 fps robot whose observation of ``tick`` (index = tick) has just reached the server."""
    est = DelayEstimator()
    est.add_exchange(-1.0, -1.0 + ONE_WAY, -1.0 + ONE_WAY, -1.0 + 2 * ONE_WAY)  # offset 0, exact delay
    m = RobotMirror(RobotSpec(name, 20.0, 10, 1, h_max, 1.0, "fast"), est)
    m.on_observation(tick, tick / 20.0, tick / 20.0 + ONE_WAY)
    return m


def test_waits_for_an_observation_whose_chunk_lands_as_early():
    # Observation of tick 2 (0.100 s) is held; the device is free at 0.146 s and the next one
    # lands at 0.15375 s. Served now, the chunk (73 ms) lands at 0.22275 s, before tick 5
    # (0.25 s); served at 0.15375 + 2 ms margin it lands at 0.2325 s: the same tick, fresher.
    m = robot("a", 2)
    assert hold_until([m], [m], 0.146, D, max_wait_s=0.010, margin_s=0.002) == pytest.approx(0.15575)
    # Not beyond the wait cap, and not when the margin pushes the chunk past the tick.
    assert hold_until([m], [m], 0.146, D, max_wait_s=0.005, margin_s=0.002) is None
    assert hold_until([m], [m], 0.146, D, max_wait_s=0.050, margin_s=0.020) is None
    # Off: never.
    assert hold_until([m], [m], 0.146, D, max_wait_s=0.0, margin_s=0.002) is None


def test_no_wait_when_it_delays_the_next_batch_for_a_robot_about_to_run_dry():
    m = robot("a", 2)
    other = robot("b", 2)
    # b ran dry at its last observation (no chunk): the batch after this one must reach it as
    # early as possible, and a wait of ~10 ms pushes that chunk past a tick boundary
    # (0.146 + 73 + 73 ms + 3.75 ms = 0.29575 s < 0.30 s; waited: 0.30575 s).
    assert hold_until([m, other], [m], 0.146, D, max_wait_s=0.010, margin_s=0.002) is None


class AlwaysHold(EarliestDeadlineScheduler):
    """EDF that asks to wait a whole second at every decision (the dispatcher must cap it)."""

    def hold(self, robots, batch, now):
        return now + 1.0


def test_dispatcher_books_nothing_while_waiting_and_caps_the_total_wait():
    m = robot("a", 2)
    sched = AlwaysHold(LatencyProfile("t", tuple(1000 * d for d in D)), 3)
    sched.max_wait_s = 0.010
    disp = Dispatcher(sched)
    plan = disp.plan([m], 0.146)
    assert plan.wait_until == pytest.approx(0.156) and plan.requests == []
    assert m.is_useful() and m.queue == [] and m.last_served_index is None  # nothing booked
    again = disp.plan([m], 0.150)  # woken early (an observation landed): the cap still counts from 0.146
    assert again.wait_until == pytest.approx(0.156)
    done = disp.plan([m], 0.156)
    assert done.wait_until is None and done.robot_ids == ["a"]
    assert disp.holds == 2 and disp.held_s == pytest.approx(0.010)
    # The next free device may wait again, from its own start.
    assert disp.plan([robot("b", 5)], 0.400).wait_until == pytest.approx(0.410)


def test_a_hold_that_raises_is_isolated_live_and_surfaces_offline():
    class Broken(EarliestDeadlineScheduler):
        def hold(self, robots, batch, now):
            raise RuntimeError("boom")

    sched = Broken(LatencyProfile("t", tuple(1000 * d for d in D)), 3)
    sched.max_wait_s = 0.010
    assert Dispatcher(sched, isolate_failures=True).plan([robot("a", 2)], 0.146).robot_ids == ["a"]
    with pytest.raises(RuntimeError, match="boom"):
        Dispatcher(sched).plan([robot("a", 2)], 0.146)


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf])
def test_bad_wait_knobs_are_refused_with_their_name(bad):
    with pytest.raises(ConfigError, match="scheduler.wait_ms"):
        make_scheduler_config("edf", wait_ms=bad).make(load_profile("l40s-pi05"), 3)
    with pytest.raises(ConfigError, match="scheduler.wait_margin_ms"):
        make_scheduler_config("edf", wait_ms=5, wait_margin_ms=bad).make(load_profile("l40s-pi05"), 3)


def test_make_applies_the_timing_and_labels_it():
    cfg = make_scheduler_config("rollout", wait_ms=10, wait_margin_ms=1)
    sched = cfg.make(load_profile("l40s-pi05"), 3)
    assert sched.max_wait_s == pytest.approx(0.010) and sched.wait_margin_s == pytest.approx(0.001)
    assert cfg.label() == "rollout +wait 10 ms"
    assert make_scheduler_config("edf").make(load_profile("l40s-pi05"), 3).max_wait_s == 0.0


@pytest.mark.parametrize("name", ["edf", "rollout"])
def test_simulator_honours_waits_and_stays_deterministic(name):
    preset = get_preset("libero")
    specs = fleet_specs(preset, "all-fast", 3)
    net = LogNormalDelay(0.00375, 0.2)

    def run(wait_ms):
        sched = make_scheduler_config(name, wait_ms=wait_ms).make(load_profile("l40s-pi05"), 3)
        return FleetSimulator(specs, sched, 10.0, net, net, seed=3, warmup_s=2.0).run()

    timed, again, plain = run(10.0), run(10.0), run(0.0)
    assert timed.held_s > 0 and plain.held_s == 0
    assert [r.executed_steps for r in timed.robots] == [r.executed_steps for r in again.robots]
    # Scored after the warm-up: 8 s of 20 fps ticks per robot.
    assert all(159 <= r.ticks <= 161 for r in timed.robots)
    # A wait holds at most 10 ms per free device: the device still serves nearly as many batches.
    assert sum(timed.batch_sizes.values()) >= 0.9 * sum(plain.batch_sizes.values())


def test_live_loop_waits_and_keeps_serving(engine):
    """The live loop honours a wait (capped, woken by observations) and every robot is still served."""
    from lerobot_armory.schedulers import EarliestDeadlineConfig
    from lerobot_armory.entrypoints.server import ArmoryServer
    from lerobot_armory.entrypoints.grpc.service import PolicyInfo
    from tests.support.pusher import Pusher, wait_for

    profile = LatencyProfile("test", (20.0, 24.0, 28.0, 32.0))
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    srv = ArmoryServer(engine, info, profile, EarliestDeadlineConfig(), 3, port=0, max_message_bytes=256 << 10)
    sched = srv.loop.scheduler
    sched.max_wait_s = 0.015
    sched.hold = lambda robots, batch, now: now + 1.0  # always ask for more than the cap
    srv.start()
    try:
        robots = [Pusher(srv.address, engine, k).start() for k in range(3)]
        assert wait_for(lambda: all(len(r.chunks) >= 4 for r in robots), timeout=20)
        for r in robots:
            r.stop()
    finally:
        srv.stop(grace_s=0.5)
    disp = srv.loop.dispatcher
    assert disp.holds > 0 and disp.held_s > 0
    assert srv.loop.stats.batches >= 4
    # Capped: never more than max_wait_s per dispatched batch.
    assert disp.held_s <= 0.015 * srv.loop.stats.batches + 0.015
