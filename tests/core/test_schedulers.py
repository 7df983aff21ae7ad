"""Schedulers on hand-built mirror states: RR rotation, EDF deadlines, Lookahead's choices."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile, load_profile
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.schedulers import (
    EarliestDeadlineScheduler,
    LookaheadConfig,
    LookaheadScheduler,
    RoundRobinScheduler,
    Scheduler,
    SchedulerConfig,
    check_batch,
    make_scheduler_config,
    scheduler_names,
    useful,
)
from lerobot_armory.sim import FleetSimulator, LogNormalDelay, fleet_specs, get_preset
from lerobot_armory.sim.cli import main as sim_main
from tests.support.mirrors import mirror, served

PROFILE = load_profile("l40s-pi05")  # 73.0, 109.8, 142.4 ms for b = 1, 2, 3


def ids(batch: Sequence[RobotMirror]) -> list[str]:
    return [r.spec.robot_id for r in batch]


# ------------------------------------------------------------------------------------------
# Round Robin


def fresh(n: int) -> list[RobotMirror]:
    """n robots, each with one never-served observation (all useful)."""
    robots = [mirror(f"r{k}") for k in range(n)]
    for r in robots:
        r.on_observation(0, 0.0, 0.0)
    return robots


class TestRoundRobin:
    def test_rotation_wraps(self):
        robots = fresh(5)
        rr = RoundRobinScheduler(PROFILE, 2)
        assert [ids(rr.select(robots, 0.0)) for _ in range(4)] == [
            ["r0", "r1"],
            ["r2", "r3"],
            ["r4", "r0"],
            ["r1", "r2"],
        ]

    def test_skips_robots_that_are_not_useful(self):
        robots = fresh(5)
        served(robots[2], 0.1)
        served(robots[3], 0.1)
        assert not robots[2].is_useful() and not robots[3].is_useful()
        rr = RoundRobinScheduler(PROFILE, 2)
        assert [ids(rr.select(robots, 0.0)) for _ in range(4)] == [
            ["r0", "r1"],
            ["r4", "r0"],
            ["r1", "r4"],
            ["r0", "r1"],
        ]

    def test_pointer_moves_past_last_taken_as_usefulness_changes(self):
        robots = fresh(4)
        rr = RoundRobinScheduler(PROFILE, 3)
        batch = rr.select(robots, 0.0)
        assert ids(batch) == ["r0", "r1", "r2"]
        for r in batch:
            served(r, 0.1)
        # Only r3 is useful now: a short batch, not padded with stale requests.
        assert ids(rr.select(robots, 0.1)) == ["r3"]
        served(robots[3], 0.2)
        for k, r in enumerate(robots):
            r.on_observation(1, 0.3, 0.3)
        # The pointer is past r3: the next batch starts again at r0.
        assert ids(rr.select(robots, 0.3)) == ["r0", "r1", "r2"]

    def test_cap_larger_than_fleet(self):
        robots = fresh(3)
        rr = RoundRobinScheduler(PROFILE, 5)
        assert ids(rr.select(robots, 0.0)) == ["r0", "r1", "r2"]
        assert ids(rr.select(robots, 0.0)) == ["r0", "r1", "r2"]

    def test_robot_leaving_does_not_break_rotation(self):
        robots = fresh(4)
        rr = RoundRobinScheduler(PROFILE, 2)
        assert ids(rr.select(robots, 0.0)) == ["r0", "r1"]
        # r1 (the pointer's robot) leaves: rotation restarts at the first robot.
        remaining = [robots[0], robots[2], robots[3]]
        assert ids(rr.select(remaining, 0.0)) == ["r0", "r2"]
        assert ids(rr.select(remaining, 0.0)) == ["r3", "r0"]

    def test_nobody_useful_gives_empty_batch(self):
        robots = [mirror("a"), mirror("b")]
        assert RoundRobinScheduler(PROFILE, 2).select(robots, 0.0) == []


# ------------------------------------------------------------------------------------------
# Earliest Deadline First


def with_chunk(robot_id: str, h_max: int, h_min: int = 1, t0: float = 0.0) -> RobotMirror:
    """fps=10: observed index 0 at t0, served at once (chunk of h_max arrives at t0), then
    observed index 1 at t0 + 0.1. Its deadline is t0 + 0.1 + (h_max - 1) / 10."""
    m = mirror(robot_id, fps=10.0, h_max=h_max, h_min=h_min)
    m.on_observation(0, t0, t0)
    served(m, t0)
    m.on_observation(1, t0 + 0.1, t0 + 0.1)
    return m


class TestEarliestDeadline:
    def setup_robots(self):
        never = mirror("never", fps=10.0, h_max=5)
        never.on_observation(1, 0.1, 0.1)  # never served: dry right now
        stale = with_chunk("stale", h_max=2, h_min=2, t0=-0.2)  # runs dry first but not useful
        robots = [with_chunk("h6", 6), with_chunk("h2", 2), never, stale, with_chunk("h8", 8), with_chunk("h4", 4)]
        return {r.spec.robot_id: r for r in robots}, robots

    def test_deadlines_by_hand(self):
        by_id, _ = self.setup_robots()
        assert by_id["h2"].deadline() == pytest.approx(0.2)
        assert by_id["h4"].deadline() == pytest.approx(0.4)
        assert by_id["h6"].deadline() == pytest.approx(0.6)
        assert by_id["h8"].deadline() == pytest.approx(0.8)
        assert by_id["never"].deadline() == pytest.approx(0.1)
        assert by_id["stale"].deadline() == pytest.approx(0.0)
        assert not by_id["stale"].is_useful()

    @pytest.mark.parametrize(
        "cap, expected",
        [(1, ["never"]), (2, ["never", "h2"]), (3, ["never", "h2", "h4"]), (5, ["never", "h2", "h4", "h6", "h8"])],
    )
    def test_picks_the_soonest_useful_deadlines(self, cap, expected):
        _, robots = self.setup_robots()
        assert ids(EarliestDeadlineScheduler(PROFILE, cap).select(robots, 0.1)) == expected

    def test_ties_keep_registration_order(self):
        robots = [with_chunk("b", 4), with_chunk("a", 4), with_chunk("c", 4)]
        assert ids(EarliestDeadlineScheduler(PROFILE, 2).select(robots, 0.1)) == ["b", "a"]

    def test_in_flight_chunk_counts_for_the_deadline(self):
        # Same state, but one robot's next chunk is still in inference: its deadline is later.
        a, b = with_chunk("a", 4), with_chunk("b", 4)
        served(b, 0.15)  # chunk (1..4) arrives at 0.15, in time to extend the run by one step
        b.on_observation(2, 0.2, 0.2)
        assert b.deadline() == pytest.approx(0.5)
        assert a.deadline() == pytest.approx(0.4)
        assert ids(EarliestDeadlineScheduler(PROFILE, 1).select([b, a], 0.2)) == ["a"]


# ------------------------------------------------------------------------------------------
# Lookahead
#
# fps=5 (ticks every 0.2 s), H = h_max = 10, h_min = 1; decision at now = 0.2, so the 1-second
# window holds 5 ticks. A "covered" robot holds a chunk reaching 9 steps past its index: any new
# chunk adds nothing inside the window (marginal gain 0). A "starving" robot has no chunk: a chunk
# dispatched now arrives before tick 1 (d_infer <= 142 ms) and adds 4 executed ticks = 0.8 s.

NOW = 0.2


def covered(robot_id: str, weight: float = 1.0) -> RobotMirror:
    m = mirror(robot_id, fps=5.0, chunk_size=10, h_max=10, weight=weight)
    m.on_observation(0, 0.0, 0.0)
    served(m, 0.0)
    m.on_observation(1, NOW, NOW)
    assert m.is_useful()
    return m


def starving(robot_id: str, weight: float = 1.0) -> RobotMirror:
    m = mirror(robot_id, fps=5.0, chunk_size=10, h_max=10, weight=weight)
    m.on_observation(0, NOW, NOW)
    return m


def la(cap: int, **kwargs) -> LookaheadScheduler:
    return LookaheadScheduler(PROFILE, cap, **kwargs)


class TestLookahead:
    def test_setup_gains_by_hand(self):
        c, s = covered("c"), starving("s")
        cv, sv = c.window_view(NOW, 1.0), s.window_view(NOW, 1.0)
        assert cv.window_ticks == sv.window_ticks == 5
        assert cv.executed() == 5
        assert cv.executed([(1, 11, 1)]) == 5  # nothing to gain
        assert sv.executed() == 0
        assert sv.arrival_tick(NOW + PROFILE.latency_s(3)) == 1
        assert sv.executed([(0, 10, 1)]) == 4

    def test_prefers_the_starving_robot_over_the_covered_one(self):
        robots = [covered("c"), starving("s")]
        assert ids(la(1).select(robots, NOW)) == ["s"]
        # RR, by contrast, takes the first robot in the ring.
        assert ids(RoundRobinScheduler(PROFILE, 1).select(robots, NOW)) == ["c"]

    def test_heavier_robot_wins_a_tie(self):
        assert ids(la(1).select([starving("light"), starving("heavy", weight=3.0)], NOW)) == ["heavy"]
        assert ids(la(1).select([starving("heavy", weight=3.0), starving("light")], NOW)) == ["heavy"]
        # With equal weights the tie goes to registration order.
        assert ids(la(1).select([starving("first"), starving("second")], NOW)) == ["first"]

    def test_weight_can_outbid_a_larger_raw_gain(self):
        # "partial" (h_max=3) holds a chunk covering indices 1, 2 of the window (ticks 0, 1); a new
        # chunk from index 1 covers 1..3, so it adds one tick (index 3 at tick 2): 1 x 5/5 = 1.0 s.
        # "full" gains 4 ticks at weight 1: 0.8 s.
        partial = mirror("partial", fps=5.0, chunk_size=10, h_max=3, weight=5.0)
        partial.on_observation(0, 0.0, 0.0)
        served(partial, 0.0)
        partial.on_observation(1, NOW, NOW)
        pv = partial.window_view(NOW, 1.0)
        assert pv.executed() == 2 and pv.executed([(1, 4, 1)]) == 3
        full = starving("full")
        assert ids(la(1).select([full, partial], NOW)) == ["partial"]
        full_heavy = starving("full", weight=5.0)
        assert ids(la(1).select([full_heavy, partial], NOW)) == ["full"]

    def test_does_not_over_batch(self):
        robots = [covered("c1"), starving("s"), covered("c2")]
        batch = la(3).select(robots, NOW)
        assert ids(batch) == ["s"]
        # EDF and RR fill the cap.
        assert len(EarliestDeadlineScheduler(PROFILE, 3).select(robots, NOW)) == 3
        assert len(RoundRobinScheduler(PROFILE, 3).select(robots, NOW)) == 3

    def test_marginal_batches_all_starving_robots(self):
        # 0.8 s gained per robot: 0.8/0.073 < 1.6/0.1098 < 2.4/0.1424 -> batch of 3.
        robots = [covered("c1"), starving("s1"), covered("c2"), starving("s2"), covered("c3"), starving("s3")]
        assert sorted(ids(la(3).select(robots, NOW))) == ["s1", "s2", "s3"]

    def test_robots_without_observation_are_ignored(self):
        robots = [mirror("ghost", fps=5.0, chunk_size=10, h_max=10), starving("s"), covered("c")]
        assert ids(la(3).select(robots, NOW)) == ["s"]

    def test_depth_two_returns_a_valid_batch(self):
        robots = [covered("c1"), starving("s1"), covered("c2"), starving("s2")]
        sched = la(2, depth=2, time_budget_ms=1000.0)
        batch = sched.select(robots, NOW)
        check_batch(batch, 2, "lookahead")
        assert set(ids(batch)) <= {"s1", "s2"}

    @pytest.mark.parametrize(
        "kwargs, field",
        [
            (dict(depth=0), "scheduler.depth"),
            (dict(window_s=0.0), "scheduler.window_s"),
            (dict(time_budget_ms=-1.0), "scheduler.time_budget_ms"),
        ],
    )
    def test_bad_knobs(self, kwargs, field):
        with pytest.raises(ConfigError) as info:
            la(3, **kwargs)
        assert info.value.field == field


# ------------------------------------------------------------------------------------------
# Contract and registry


class TestCheckBatch:
    def robots(self):
        rs = fresh(3)
        served(rs[2], 0.1)  # not useful any more
        return rs

    def test_accepts_a_valid_batch(self):
        rs = self.robots()
        check_batch(rs[:2], 2, "x")

    @pytest.mark.parametrize(
        "pick, cap, match",
        [
            (lambda rs: [], 3, "empty"),
            (lambda rs: rs[:2], 1, "above the cap"),
            (lambda rs: [rs[0], rs[0]], 3, "twice"),
            (lambda rs: [rs[0], rs[2]], 3, "not useful"),
        ],
    )
    def test_rejects(self, pick, cap, match):
        with pytest.raises(RuntimeError, match=match):
            check_batch(pick(self.robots()), cap, "x")


def test_useful_filters_in_order():
    rs = fresh(4)
    served(rs[1], 0.1)
    assert ids(useful(rs)) == ["r0", "r2", "r3"]


def test_max_batch_size_below_one():
    with pytest.raises(ConfigError) as info:
        RoundRobinScheduler(PROFILE, 0)
    assert info.value.field == "max_batch_size"


def test_scheduler_d_infer_table_covers_the_cap():
    s = EarliestDeadlineScheduler(PROFILE, 7)
    assert len(s.d_infer) == 7
    assert s.d_infer[0] == pytest.approx(0.073)
    assert s.d_infer[6] == pytest.approx((211.1 + 2 * 33.6) / 1000)


def test_registry_names_and_configs():
    names = scheduler_names()
    assert {"rr", "edf", "lookahead"} <= set(names)
    assert names == sorted(names)
    cfg = make_scheduler_config("lookahead", depth=2)
    assert isinstance(cfg, LookaheadConfig)
    assert cfg.type == "lookahead"
    assert cfg.label() == "lookahead L=2"
    sched = cfg.build(PROFILE, 3)
    assert isinstance(sched, LookaheadScheduler) and sched.depth == 2
    assert isinstance(make_scheduler_config("rr").build(PROFILE, 2), RoundRobinScheduler)
    assert isinstance(make_scheduler_config("edf").build(PROFILE, 2), EarliestDeadlineScheduler)
    assert make_scheduler_config("edf").label() == "edf"


def test_unknown_scheduler():
    with pytest.raises(ConfigError) as info:
        make_scheduler_config("nope")
    assert info.value.field == "scheduler.type"
    assert "lookahead" in info.value.message


# A fourth scheduler registered from outside the package: always serves the last useful robot alone.
CALLS: list[int] = []


class LastUsefulScheduler(Scheduler):
    def select(self, robots, now):
        CALLS.append(len(robots))
        return useful(robots)[-1:]


@SchedulerConfig.register_subclass("test-fourth")
@dataclass
class FourthConfig(SchedulerConfig):
    def build(self, profile: LatencyProfile, max_batch_size: int) -> Scheduler:
        return LastUsefulScheduler(profile, max_batch_size)


def test_fourth_scheduler_is_registered_and_runs_in_the_simulator():
    assert "test-fourth" in scheduler_names()
    cfg = make_scheduler_config("test-fourth")
    assert isinstance(cfg, FourthConfig) and cfg.type == "test-fourth"
    sched = cfg.build(PROFILE, 3)
    specs = fleet_specs(get_preset("libero"), "half-fast", 4)
    CALLS.clear()
    net = LogNormalDelay(0.00375, 0.0)
    result = FleetSimulator(specs, sched, 5.0, net, net, seed=0).run()
    assert set(result.batch_sizes) == {1}
    assert result.batch_sizes[1] == len(CALLS) > 0
    assert all(n == 4 for n in CALLS)
    # It always favours the last robot in the ring: that robot is served and fares best.
    assert result.robots[-1].executed_steps > 0
    assert result.robots[-1].starvation_pct <= min(r.starvation_pct for r in result.robots)


def test_fourth_scheduler_from_the_command_line(capsys, tmp_path):
    import json

    out = tmp_path / "r.json"
    sim_main(["--scheduler.type=test-fourth", "--robots=3", "--duration_s=3", f"--output={out}"])
    run = json.loads(out.read_text())["runs"][0]
    assert run["scheduler"] == "test-fourth"
    assert set(run["batch_sizes"]) == {"1"}
    assert "test-fourth" in capsys.readouterr().out
