"""The chunk mirror: the transition on the tick grid, delay estimation, the server's mirror."""

from __future__ import annotations

import math
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import load_profile
from lerobot_armory.delay import DelayEstimator
from lerobot_armory.mirror import MAX_AWAITING_REPORTS, RobotMirror, RobotTimeline, reward
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.transition import Chunk, advance, dry_tick, index_at, observed_tick, queue_of, queue_with, reach, tick_of, tick_reaching, ticks_until_dry
from lerobot_armory.schedulers import make_scheduler_config
from lerobot_armory.sim import FleetSimulator, LogNormalDelay, fleet_specs, get_preset
from tests.support.mirrors import consistent_chunks, mirror, naive_run, served, spec


def record_uses(index, chunks, n_ticks):
    calls = []
    end = advance(index, chunks, n_ticks, lambda pos, off: calls.append((pos, off)))
    return end, calls


# ------------------------------------------------------------------------------------------
# tick_of


class TestTickOf:
    def test_arrival_exactly_at_a_tick_counts_as_arrived_at_that_tick(self):
        # 0.15 * 20 is 3.0000000000000004 in floats: still tick 3, not 4.
        assert tick_of(0.15, 0.0, 20.0) == 3
        assert tick_of(0.1 + 3 / 20, 0.1, 20.0) == 3
        assert tick_of(0.0, 0.0, 20.0) == 0

    def test_just_after_a_tick_goes_to_the_next_tick(self):
        assert tick_of(0.150001, 0.0, 20.0) == 4
        assert tick_of(0.149999, 0.0, 20.0) == 3

    def test_times_before_the_anchor_give_non_positive_ticks(self):
        assert tick_of(-0.01, 0.0, 20.0) == 0  # tick 0 (t=0) is the first tick at or after -0.01
        assert tick_of(-0.05, 0.0, 20.0) == -1
        assert tick_of(-0.06, 0.0, 20.0) == -1

    @given(
        anchor=st.floats(-100, 100, allow_nan=False),
        fps=st.sampled_from([5.0, 10.0, 15.0, 20.0, 30.0, 60.0, 7.3]),
        k=st.integers(-1000, 10000),
    )
    def test_tick_time_maps_back_to_its_own_tick(self, anchor, fps, k):
        assert tick_of(anchor + k / fps, anchor, fps) == k


# ------------------------------------------------------------------------------------------
# advance: hand-computed cases


class TestAdvanceByHand:
    def test_single_chunk_arriving_at_tick_3_over_10_ticks(self):
        # ticks 0-2 starve (not arrived), 3-7 execute indices 0..4, 8-9 starve (chunk ran out).
        end = advance(0, [(0, 5, 3)], 10)
        assert end == 5
        executed = end - 0
        assert executed == 5 and 10 - executed == 5

    def test_tick_by_tick_prefix_of_that_case(self):
        chunks = [(0, 5, 3)]
        assert [advance(0, chunks, n) for n in range(11)] == [0, 0, 0, 0, 1, 2, 3, 4, 5, 5, 5]

    def test_no_chunks_starves_every_tick(self):
        assert advance(7, [], 100) == 7

    def test_zero_or_negative_ticks_run_nothing(self):
        assert advance(3, [(0, 10, 0)], 0) == 3
        assert advance(3, [(0, 10, 0)], -4) == 3

    def test_chunk_arrived_before_tick_0_is_usable_at_tick_0(self):
        assert advance(2, [(0, 5, -7)], 10) == 5

    def test_chunk_not_covering_the_index_is_useless(self):
        # Robot at index 6; the chunk covers 0..4 only.
        assert advance(6, [(0, 5, 0)], 10) == 6
        # Chunk starting after the index: the robot never reaches it.
        assert advance(0, [(3, 8, 0)], 10) == 0

    def test_overlapping_chunks_switch_to_the_newest(self):
        # A covers 0..4 from tick 0; B (made at index 2) covers 2..6 and arrives at tick 3.
        # Ticks 0-2 execute 0,1,2 from A; at tick 3 (index 3) the robot switches to B at
        # offset 1 and runs B to its end: indices 3..6 at ticks 3..6; ticks 7-9 starve.
        end, calls = record_uses(0, [(0, 5, 0), (2, 7, 3)], 10)
        assert end == 7
        assert calls == [(0, 0), (1, 1)]

    def test_late_chunk_extends_the_run_even_after_starving(self):
        # A runs out at tick 5 (index 5); B (made at index 2) arrives at tick 8 and covers 5,6.
        end, calls = record_uses(0, [(0, 5, 0), (2, 7, 8)], 12)
        assert end == 7  # ticks 0-4 A, 5-7 starve, 8-9 B, 10-11 starve
        assert calls == [(0, 0), (1, 3)]

    def test_chunk_arriving_after_the_robot_passed_its_end_is_never_used(self):
        # B covers 0..3 but arrives at tick 6, when A already carried the robot to index 6.
        chunks = [(0, 4, 6), (0, 10, 0)]
        end, calls = record_uses(0, chunks, 12)
        assert end == 10
        assert {pos for pos, _ in calls} == {1}
        assert calls[0] == (1, 0)

    def test_equal_start_newer_chunk_wins(self):
        # Two chunks from the same observation index: the later one in the list is newer.
        end, calls = record_uses(0, [(0, 5, 0), (0, 5, 0)], 3)
        assert end == 3
        assert calls == [(1, 0)]

    def test_reach_follows_overlapping_arrived_chunks(self):
        chunks = [(0, 3, 0), (2, 6, 1), (5, 9, 5)]
        assert reach(0, chunks, 0) == 3
        assert reach(0, chunks, 1) == 6
        assert reach(0, chunks, 5) == 9
        assert reach(7, chunks, 4) == 7  # the only chunk covering 7 has not arrived


class TestTicksUntilDry:
    def test_single_future_chunk(self):
        # Arrives at tick 3, runs indices 0..4 on ticks 3..7, dry at tick 8.
        assert ticks_until_dry(0, [(0, 5, 3)]) == 8

    def test_already_arrived_chunk(self):
        assert ticks_until_dry(2, [(0, 5, -3)]) == 3

    def test_no_chunks_or_uncovered_index_is_dry_now(self):
        assert ticks_until_dry(4, []) == 0
        assert ticks_until_dry(7, [(0, 5, 0)]) == 0

    def test_gap_before_a_late_chunk(self):
        # A runs 0..4 (ticks 0..4), starves 5..8, B (made at 3) covers 5..7 from tick 9.
        assert ticks_until_dry(0, [(0, 5, 0), (3, 8, 9)]) == 12

    def test_chunk_arriving_after_the_gap_it_could_have_filled(self):
        # A runs out at tick 2 (index 2); B arrives at 10 and still covers index 2..5.
        assert ticks_until_dry(0, [(0, 2, 0), (1, 6, 10)]) == 14


@pytest.mark.parametrize("fps, one_way", [(10.0, 0.0), (20.0, 0.00375), (30.0, 0.1234)])
def test_observed_tick_is_the_latest_arrived_observation(fps, one_way):
    origin = 3.7
    for k in range(0, 50):
        landed = origin + k / fps + one_way  # the observation of tick k reaches the server
        assert observed_tick(landed, origin, fps, one_way) == k
        assert observed_tick(landed - 1e-6, origin, fps, one_way) == k - 1
    # At the origin itself, the latest observation is from one-way delay's worth of ticks earlier.
    assert observed_tick(origin, origin, fps, one_way) == -math.ceil(one_way * fps - 1e-9)


# ------------------------------------------------------------------------------------------
# advance: properties

chunk_lists = st.lists(
    st.tuples(st.integers(0, 30), st.integers(1, 10), st.integers(-5, 45)), max_size=6
).map(lambda cs: sorted(((s, s + h, a) for s, h, a in cs), key=lambda c: c[0]))
indices = st.integers(0, 30)
tick_counts = st.integers(0, 60)


@settings(max_examples=200, deadline=None)
@given(index=indices, chunks=chunk_lists, n=tick_counts)
def test_advance_matches_tick_by_tick_reference(index, chunks, n):
    end = advance(index, chunks, n)
    ref_end, executed, starved, _ = naive_run(index, chunks, n)
    assert end == ref_end
    assert end - index == executed
    assert executed + starved == n
    assert 0 <= executed <= n


@settings(max_examples=150, deadline=None)
@given(index=indices, chunks=chunk_lists, n=tick_counts)
def test_index_never_decreases_tick_after_tick(index, chunks, n):
    ends = [advance(index, chunks, k) for k in range(n + 1)]
    assert ends[0] == index
    for a, b in zip(ends, ends[1:]):
        assert b - a in (0, 1)  # one tick executes at most one step and never goes back


@settings(max_examples=200, deadline=None)
@given(index=indices, chunks=chunk_lists, n=tick_counts, data=st.data())
def test_splitting_a_run_in_two_gives_the_same_index(index, chunks, n, data):
    k = data.draw(st.integers(0, n))
    mid = advance(index, chunks, k)
    renumbered = [(s, e, a - k) for s, e, a in chunks]
    assert advance(mid, renumbered, n - k) == advance(index, chunks, n)


@settings(max_examples=200, deadline=None)
@given(
    index=indices,
    chunks=chunk_lists,
    n=tick_counts,
    extra=st.tuples(st.integers(0, 30), st.integers(1, 10), st.integers(-5, 45)),
)
def test_adding_a_chunk_never_decreases_executed_steps(index, chunks, n, extra):
    s, h, a = extra
    more = sorted([*chunks, (s, s + h, a)], key=lambda c: c[0])
    assert advance(index, more, n) >= advance(index, chunks, n)


requests = st.lists(st.tuples(st.integers(0, 40), st.integers(0, 8), st.integers(1, 10)), max_size=8)


@settings(max_examples=200, deadline=None)
@given(index=indices, reqs=requests, n=st.integers(1, 50))
def test_first_use_offsets_follow_the_switch_rule(index, reqs, n):
    """For chunks a real robot can get, the first on_use call per chunk is the naive-async
    switch (newest covering chunk) and its offset is in [0, h): a chunk never covers an index
    before its observation index."""
    chunks = consistent_chunks(index, reqs, n)
    end, calls = record_uses(index, chunks, n)
    first: dict[int, int] = {}
    for pos, off in calls:
        first.setdefault(pos, off)
    ref_end, _, _, ref_first = naive_run(index, chunks, n)
    assert end == ref_end
    assert first == ref_first
    for pos, off in calls:
        s, e, _ = chunks[pos]
        assert 0 <= off < e - s


def test_on_use_called_only_on_a_switch():
    # A covers everything; an unrelated chunk B (never covering the index in time) arrives at tick 5.
    _, calls = record_uses(0, [(0, 10, 0), (20, 30, 5)], 10)
    assert calls == [(0, 0)]  # got [(0, 0), (0, 5)]


# ------------------------------------------------------------------------------------------
# The coverage-queue form (the schedulers' rollouts) agrees with advance()


def realistic_chunks(rnd: random.Random, index: int) -> list[tuple[int, int, int]]:
    """Chunks a robot could hold: each starts at or before the index it has when it arrives."""
    chunks: list[tuple[int, int, int]] = []
    for _ in range(rnd.randint(0, 4)):
        arrival = rnd.randint(-3, 15)
        at = advance(index, sorted(chunks), arrival) if arrival > 0 else index
        start = rnd.randint(max(0, at - 8), at)
        chunks.append((start, start + rnd.randint(1, 10), arrival))
    return sorted(chunks)


def test_queue_form_agrees_with_advance_on_random_chunk_sets():
    rnd = random.Random(7)
    for _ in range(3000):
        index = rnd.randint(0, 5)
        chunks = realistic_chunks(rnd, index)
        q = queue_of(index, chunks)
        for tick in range(0, 25):
            assert index_at(index, q, tick) == advance(index, chunks, tick)
        target = index + rnd.randint(0, 8)
        first = next((k for k in range(60) if advance(index, chunks, k) >= target), -1)
        assert tick_reaching(index, q, target) == first
        # Dry tick: with every chunk that can still extend the coverage arrived.
        useful = [(s, e, a) for s, e, a in chunks if e > index]
        last = max([a for _, _, a in useful if a > 0], default=0)
        at = advance(index, chunks, last)
        assert dry_tick(index, q) == last + reach(at, chunks, last) - at




@settings(max_examples=300, deadline=None)
@given(index=indices, reqs=requests, n=st.integers(1, 50), ahead=st.integers(0, 12), data=st.data())
def test_queue_form_agrees_with_advance(index, reqs, n, ahead, data):
    """index_at / tick_reaching / dry_tick / queue_with are advance() on chunks a robot can get."""
    chunks = consistent_chunks(index, reqs, n)
    q = queue_of(index, chunks)
    for tick in range(n + 5):
        assert index_at(index, q, tick) == advance(index, chunks, tick)
    target = index + ahead
    first = next((k for k in range(4 * n + 100) if advance(index, chunks, k) >= target), -1)
    assert tick_reaching(index, q, target) == first
    dry = dry_tick(index, q)
    assert all(index_at(index, q, dry + k) == index_at(index, q, dry) for k in range(6))  # dry: it starves from then on
    last = max([a for _, e, a in chunks if e > index and a > 0], default=0)
    at = advance(index, chunks, last)
    assert dry_tick(index, q) == last + reach(at, chunks, last) - at
    # One more chunk made from the observation of some tick, arriving later: queue_with == adding it.
    obs_tick = data.draw(st.integers(0, n))
    arrival = obs_tick + data.draw(st.integers(0, 10))
    start = advance(index, chunks, obs_tick)
    extra = (start, start + data.draw(st.integers(1, 10)), arrival)
    q2 = queue_with(q, arrival, extra[1])
    more = sorted([*chunks, extra])
    for tick in range(n + 15):
        assert index_at(index, q2, tick) == advance(index, more, tick)


# ------------------------------------------------------------------------------------------
# RobotTimeline


class TestRobotTimeline:
    def test_tick_times_and_ticks_before(self):
        tl = RobotTimeline(fps=20.0, anchor=0.01)
        assert tl.tick_time(0) == pytest.approx(0.01)
        assert tl.tick_time(4) == pytest.approx(0.21)
        assert tl.ticks_before(0.01) == 0  # tick 0 is not strictly before its own time
        assert tl.ticks_before(0.0100001) == 1
        assert tl.ticks_before(0.21) == 4
        assert tl.ticks_before(-5.0) == 0

    def test_add_chunk_keeps_order_and_run_to_reports_uses(self):
        tl = RobotTimeline(fps=10.0, anchor=0.0)
        b = Chunk(1, 2, 5, 0.25)  # covers 2..6, arrives at tick 3 (t=0.25 -> tick 3)
        a = Chunk(0, 0, 5, 0.0)  # covers 0..4, arrives at tick 0
        tl.add_chunk(b)
        tl.add_chunk(a)
        assert [c.chunk_id for c in tl.chunks] == [0, 1]
        uses = []
        assert tl.run_to(4, lambda c, off: uses.append((c.chunk_id, off))) == 4
        assert tl.index == 4 and tl.tick == 4
        assert uses == [(0, 0), (1, 1)]
        # Running backwards or to the same tick does nothing.
        assert tl.run_to(2) == 0 and tl.index == 4
        assert tl.run_to(20) == 3  # indices 4, 5, 6 then dry
        assert tl.index == 7
        assert tl.chunks == []  # both chunks end at or before 7: pruned

    @settings(max_examples=100, deadline=None)
    @given(reqs=requests, cuts=st.lists(st.integers(0, 50), max_size=5))
    def test_piecewise_runs_equal_one_run_and_offsets_are_non_negative(self, reqs, cuts):
        n = 50
        tick_chunks = consistent_chunks(0, reqs, n)
        fps = 20.0

        def build():
            tl = RobotTimeline(fps, anchor=0.3)
            for k, (s, e, a) in enumerate(tick_chunks):
                tl.add_chunk(Chunk(k, s, e - s, tl.tick_time(a)))
            return tl

        whole, pieces = build(), build()
        first_whole: dict[int, int] = {}
        first_pieces: dict[int, int] = {}
        whole.run_to(n, lambda c, off: first_whole.setdefault(c.chunk_id, off))
        for cut in sorted(cuts) + [n]:
            pieces.run_to(cut, lambda c, off: first_pieces.setdefault(c.chunk_id, off))
        assert whole.index == pieces.index
        assert first_whole == first_pieces
        assert all(off >= 0 for off in first_whole.values())


def test_simulated_run_never_executes_a_chunk_before_its_observation_index():
    preset = get_preset("libero")
    specs = fleet_specs(preset, "half-fast", 6)
    sched = make_scheduler_config("edf").build(load_profile("l40s-pi05"), 3)
    net = LogNormalDelay(0.03, 0.8)  # heavy jitter: out-of-order observations, late chunks
    result = FleetSimulator(specs, sched, 20.0, net, net, seed=3).run()
    for robot, s in zip(result.robots, specs, strict=True):
        offsets = [int(k) for k in robot.first_executed_index if k != "unused"]
        assert offsets, "every robot executes at least one chunk"
        assert all(0 <= off < s.h_max for off in offsets)
        assert sum(robot.first_executed_index.values()) == robot.chunks_received


# ------------------------------------------------------------------------------------------
# RobotSpec


class TestRobotSpec:
    def test_valid_spec(self):
        s = RobotSpec("a", 20.0, 10, 1, 6, 5.0, "fast")
        assert (s.h_min, s.h_max, s.weight, s.tier) == (1, 6, 5.0, "fast")

    @pytest.mark.parametrize(
        "kwargs, field",
        [
            (dict(h_min=7, h_max=6), "h_min"),
            (dict(h_max=11), "h_max"),
            (dict(h_max=0, h_min=0), "h_max"),
            (dict(h_min=-1), "h_min"),
            (dict(fps=0.0), "fps"),
            (dict(fps=-20.0), "fps"),
            (dict(fps=math.nan), "fps"),
            (dict(fps=math.inf), "fps"),
            (dict(weight=0.0), "weight"),
            (dict(weight=-1.0), "weight"),
            (dict(weight=math.nan), "weight"),
            (dict(tier="medium"), "tier"),
            (dict(chunk_size=0, h_max=0, h_min=0), "chunk_size"),
            (dict(robot_id=""), "robot_id"),
        ],
    )
    def test_invalid_spec_names_the_field(self, kwargs, field):
        base = dict(robot_id="a", fps=20.0, chunk_size=10, h_min=1, h_max=6, weight=1.0, tier="slow")
        base.update(kwargs)
        with pytest.raises(ConfigError) as info:
            RobotSpec(**base)
        assert info.value.field == field
        assert str(info.value).startswith(f"{field}: ")


# ------------------------------------------------------------------------------------------
# DelayEstimator


class TestDelayEstimator:
    def exchange(self, est, offset, up, down, t_robot_send=1.0, processing=0.05):
        """One exchange with a true clock offset (server - robot) and one-way delays."""
        t_server_recv = t_robot_send + offset + up
        t_server_send = t_server_recv + processing
        t_robot_recv = t_server_send + down - offset
        est.add_exchange(t_robot_send, t_server_recv, t_server_send, t_robot_recv)

    def test_symmetric_delays_recover_offset_and_round_trip(self):
        est = DelayEstimator()
        self.exchange(est, offset=0.3, up=0.05, down=0.05)
        assert est.offset_s == pytest.approx(0.3)
        assert est.round_trip_s == pytest.approx(0.1)
        assert est.one_way_s == pytest.approx(0.05)
        assert est.to_server_time(2.0) == pytest.approx(2.3)
        assert est.samples == 1

    def test_negative_offset(self):
        est = DelayEstimator()
        self.exchange(est, offset=-12.5, up=0.02, down=0.02, t_robot_send=100.0)
        assert est.offset_s == pytest.approx(-12.5)
        assert est.one_way_s == pytest.approx(0.02)

    @given(
        offset=st.floats(-1000, 1000),
        up=st.floats(0, 0.5),
        down=st.floats(0, 0.5),
        t_send=st.floats(0, 1000),
    )
    def test_asymmetric_delays_keep_robot_clock_arrival_exact(self, offset, up, down, t_send):
        est = DelayEstimator()
        self.exchange(est, offset, up, down)
        # The split is not observable: half each, and the offset absorbs the asymmetry...
        assert est.one_way_s == pytest.approx((up + down) / 2, abs=1e-6)
        assert est.offset_s == pytest.approx(offset + (up - down) / 2, abs=1e-6)
        # ...so a chunk sent at server time t_send is predicted to reach the robot at the right
        # robot-clock time: t_send + d_action, minus the offset.
        predicted_robot_arrival = t_send + est.one_way_s - est.offset_s
        true_robot_arrival = t_send + down - offset
        assert predicted_robot_arrival == pytest.approx(true_robot_arrival, abs=1e-6)

    def test_ewma_after_first_sample(self):
        est = DelayEstimator(alpha=0.5)
        self.exchange(est, offset=0.0, up=0.1, down=0.1)
        self.exchange(est, offset=0.0, up=0.3, down=0.3)
        assert est.round_trip_s == pytest.approx(0.2 + 0.5 * (0.6 - 0.2))
        assert est.offset_s == pytest.approx(0.0, abs=1e-12)
        assert est.samples == 2

    def test_negative_round_trip_is_clamped(self):
        est = DelayEstimator()
        est.add_exchange(1.0, 1.0, 2.0, 1.5)  # the server claims longer processing than the round trip
        assert est.round_trip_s == 0.0


# ------------------------------------------------------------------------------------------
# RobotMirror


class TestUsefulness:
    def test_usefulness_rule(self):
        m = mirror(h_min=3, h_max=5)
        assert not m.is_useful()  # no observation yet
        assert m.on_observation(0, 0.0, 0.0)
        assert m.is_useful()  # never served
        served(m, 0.1)
        assert m.last_served_index == 0
        assert not m.is_useful()  # same observation as the last served one
        m.on_observation(0, 0.1, 0.1)  # robot starved: same index, newer observation
        assert not m.is_useful()
        m.on_observation(2, 0.3, 0.3)
        assert not m.is_useful()  # 2 < h_min steps since the last served observation
        m.on_observation(3, 0.4, 0.4)
        assert m.is_useful()  # exactly h_min steps

    def test_h_min_zero_still_needs_a_new_index(self):
        m = mirror(h_min=0, h_max=5)
        m.on_observation(4, 0.0, 0.0)
        served(m, 0.1)
        m.on_observation(4, 0.1, 0.1)
        assert not m.is_useful()
        m.on_observation(5, 0.2, 0.2)
        assert m.is_useful()

    def test_dispatch_without_observation_raises(self):
        with pytest.raises(ValueError):
            mirror().on_dispatch(1.0)


class TestObservations:
    def test_index_going_backwards_raises(self):
        m = mirror()
        m.on_observation(5, 1.0, 1.0)
        with pytest.raises(ValueError, match="backwards"):
            m.on_observation(4, 1.1, 1.1)

    def test_out_of_order_older_observation_is_ignored(self):
        m = mirror()
        assert m.on_observation(5, 1.0, 1.05)
        assert m.on_observation(3, 0.9, 1.06) is False  # captured earlier, arrived later
        assert m.obs_index == 5
        assert m.obs_capture_robot == 1.0
        assert m.obs_recv == 1.05
        # Same capture time counts as not newer either.
        assert m.on_observation(6, 1.0, 1.07) is False
        assert m.obs_index == 5

    def test_observation_prunes_chunks_that_ended(self):
        m = mirror(h_max=5)
        m.on_observation(0, 0.0, 0.0)
        served(m, 0.0)
        m.on_observation(4, 0.4, 0.4)
        assert len(m.queue) == 1
        m.on_observation(5, 0.5, 0.5)
        assert m.queue == []

    def test_dispatch_makes_chunk_from_latest_observation(self):
        m = mirror(h_max=5)
        m.on_observation(7, 0.0, 0.0)
        c = m.on_dispatch(0.2)
        assert (c.i_start, c.h, c.end, c.t_arrival) == (7, 5, 12, 0.2)
        assert m.queue == [c]


class TestPredictionsWithZeroDelays:
    """fps=10 (ticks every 0.1 s), h_max=5; observation of index 0 at t=0."""

    def make(self):
        m = mirror(fps=10.0, h_max=5)
        m.on_observation(0, 0.0, 0.0)
        return m

    def test_without_chunks(self):
        m = self.make()
        assert m.deadline() == pytest.approx(0.0)  # dry at the observation's own tick
        assert m.predicted_index(5.0) == 0
        assert mirror().deadline() == -math.inf  # no observation at all
        assert mirror().predicted_index(3.0) == 0

    def test_deadline_and_predicted_index(self):
        m = self.make()
        served(m, 0.25)  # chunk (0..4) at t=0.25 -> first usable tick 3 (t=0.3)
        # Ticks 3..7 execute indices 0..4; tick 8 (t=0.8) is the first starving tick.
        assert m.deadline() == pytest.approx(0.8)
        assert m.predicted_index(0.0) == 0
        assert m.predicted_index(0.3) == 0  # tick 3 has not happened before t=0.3
        assert m.predicted_index(0.31) == 1
        assert m.predicted_index(0.55) == 3
        assert m.predicted_index(0.8) == 5
        assert m.predicted_index(10.0) == 5

    def test_later_observation_reanchors_the_prediction(self):
        m = self.make()
        served(m, 0.25)
        m.on_observation(2, 0.5, 0.5)  # index 2 at tick 5 (robot started at tick 3)
        assert m.deadline() == pytest.approx(0.8)
        assert m.predicted_index(0.61) == 4

    def test_window_view(self):
        m = self.make()
        served(m, 0.25)
        view = m.window_view(0.45, 1.0)
        # First tick at or after 0.45 is tick 5 (t=0.5); index there is 2; window ticks 5..14.
        assert view.index == 2
        assert view.origin_time == pytest.approx(0.5)
        assert view.window_ticks == 10
        assert view.executed() == 3  # indices 2, 3, 4
        assert view.arrival_tick(0.5) == 0 and view.arrival_tick(0.51) == 1
        # A chunk made from index 2 arriving at tick 1 covers 2..6: all of it runs at ticks 0..4.
        assert view.executed([(2, 7, 1)]) == 5


class TestPredictionsWithDelays:
    def test_clock_offset_and_one_way_delay(self):
        est = DelayEstimator()
        # Robot clock is 0.5 s behind the server; one-way delays 20 ms each.
        est.add_exchange(0.0, 0.52, 0.52, 0.04)
        assert est.offset_s == pytest.approx(0.5)
        assert est.one_way_s == pytest.approx(0.02)
        m = RobotMirror(spec(fps=10.0, h_max=5), est)
        m.on_observation(10, 1.0, 1.52)  # captured at robot 1.0 == server 1.5
        assert m.obs_anchor == pytest.approx(1.5)
        chunk = m.on_dispatch(1.6)
        assert chunk.t_arrival == pytest.approx(1.62)
        # Arrival tick: first tick at or after 1.62 is tick 2 (1.7); runs 10..14 on ticks 2..6.
        assert m.deadline() == pytest.approx(2.2)
        assert m.predicted_index(1.75) == 11
        assert m.predicted_index(1.5) == 10
        assert m.predicted_index(3.0) == 15

    def test_asymmetric_network_keeps_the_mirror_on_the_robot_grid(self):
        """Offset 0.3 s, uplink 80 ms, downlink 20 ms. The estimated offset and one-way delay
        are both wrong by 30 ms, but the chunk lands on the right robot tick."""
        offset, up, down, fps = 0.3, 0.08, 0.02, 10.0
        est = DelayEstimator()
        est.add_exchange(0.0, 0.0 + offset + up, 0.0 + offset + up, 0.0 + up + down)
        m = RobotMirror(spec(fps=fps, h_max=5), est)
        capture_robot = 2.0  # robot tick 0 of this grid
        m.on_observation(0, capture_robot, capture_robot + offset + up)
        t_done = capture_robot + offset + 0.23  # server time the chunk is sent
        m.on_dispatch(t_done)
        true_arrival_robot = t_done + down - offset  # robot clock: 2.25 -> tick 3 (2.3)
        true_tick = math.ceil((true_arrival_robot - capture_robot) * fps - 1e-9)
        assert true_tick == 3
        view = m.window_view(m.obs_anchor, 2.0)
        assert view.chunks[0][2] == true_tick
        # True dry tick is 3 + 5 = 8 after the observation tick.
        assert m.deadline() - m.obs_anchor == pytest.approx(0.8)


class TestReport:
    def test_report_replaces_the_estimated_arrival(self):
        m = mirror(fps=10.0, h_max=5)
        m.on_observation(0, 0.0, 0.1)
        chunk = m.on_dispatch(0.25)
        assert chunk.t_arrival == 0.25
        assert m.deadline() == pytest.approx(0.8)
        # Symmetric 100 ms each way, clocks in sync: the chunk reached the robot at 0.35.
        assert m.on_report(chunk.chunk_id, 0.35) is True
        assert m.estimator.offset_s == pytest.approx(0.0)
        assert m.estimator.one_way_s == pytest.approx(0.1)
        assert m.queue[0].t_arrival == pytest.approx(0.35)
        # Arrival tick 4 (0.4): indices 0..4 on ticks 4..8, dry at tick 9.
        assert m.deadline() == pytest.approx(0.9)
        # Future dispatches use the learned one-way delay.
        m.on_observation(1, 0.5, 0.6)
        assert m.on_dispatch(1.0).t_arrival == pytest.approx(1.1)

    def test_report_in_robot_clock_is_converted(self):
        m = mirror(fps=10.0, h_max=5)
        # Robot clock 1 s behind, 50 ms each way: capture robot 0.0 (server 1.0), received at
        # 1.05, chunk sent 1.25, reached the robot at server 1.30 == robot 0.30.
        m.on_observation(0, 0.0, 1.05)
        chunk = m.on_dispatch(1.20)
        m.on_complete(chunk, 1.25)
        assert (chunk.capture_robot, chunk.obs_recv, chunk.t_sent) == (0.0, 1.05, 1.25)
        assert m.on_report(chunk.chunk_id, 0.30) is True
        assert m.estimator.offset_s == pytest.approx(1.0)
        assert m.queue[0].t_arrival == pytest.approx(1.30)

    def test_complete_replaces_the_predicted_send_time(self):
        m = mirror(fps=10.0, h_max=5)
        m.on_observation(0, 0.0, 0.0)
        chunk = m.on_dispatch(0.25)
        m.on_complete(chunk, 0.4)  # the batch took longer than d_infer predicted
        assert (chunk.t_sent, chunk.t_arrival) == (0.4, 0.4)
        assert m.deadline() == pytest.approx(0.9)

    def test_report_is_taken_once_and_only_between_send_and_receipt(self):
        m = mirror(fps=10.0, h_max=5)
        m.on_observation(0, 0.0, 0.1)
        chunk = m.on_dispatch(0.25)
        assert m.on_report(chunk.chunk_id, 0.35, t_report_recv=0.3) is True
        assert chunk.t_arrival == pytest.approx(0.3)  # cannot have arrived after the report came in
        assert m.on_report(chunk.chunk_id, 0.35) is None  # a second report of the same chunk: ignored
        assert m.estimator.samples == 1

    def test_report_for_unknown_chunk_changes_nothing(self):
        m = mirror(fps=10.0, h_max=5)
        m.on_observation(0, 0.0, 0.0)
        chunk = m.on_dispatch(0.25)
        assert m.on_report(99, 0.35) is None
        assert m.queue[0].t_arrival == 0.25
        assert m.queue[0] is chunk
        assert m.estimator.samples == 0

    def test_cancelled_chunk_is_not_awaited(self):
        m = mirror(fps=10.0, h_max=5)
        m.on_observation(0, 0.0, 0.0)
        chunk = m.on_dispatch(0.25)
        m.on_cancel(chunk, None)
        assert m.on_report(chunk.chunk_id, 0.3) is None
        assert m.estimator.samples == 0

    def test_awaited_reports_are_bounded(self):
        m = mirror(fps=10.0, h_min=0, h_max=5)
        n = MAX_AWAITING_REPORTS + 10
        for k in range(n):
            m.on_observation(k, 0.1 * k, 0.1 * k)
            m.on_dispatch(0.1 * k + 0.05)
        assert len(m._awaiting) == MAX_AWAITING_REPORTS
        assert m.on_report(0, 0.1) is None  # the oldest were forgotten
        assert m.on_report(n - 1, 0.1 * (n - 1) + 0.05) is True


# ------------------------------------------------------------------------------------------
# reward


def test_reward_is_weighted_executed_seconds():
    specs = [spec("a", fps=20.0, weight=1.0), spec("b", fps=10.0, weight=5.0)]
    assert reward(specs, [10, 4]) == pytest.approx(10 / 20 + 5 * 4 / 10)
    assert reward(specs, [0, 0]) == 0.0
    with pytest.raises(ValueError):
        reward(specs, [1])


@pytest.mark.parametrize("scheduler", ["edf", "lookahead"])
def test_simulated_honest_robots_are_never_clamped(scheduler, monkeypatch):
    """The progress bound never cuts an honest robot's index, under heavy network jitter
    (reordered observations, late chunks) and a saturated device."""
    import lerobot_armory.sim.simulator as simulator

    made: list[RobotMirror] = []

    class Counted(RobotMirror):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(simulator, "RobotMirror", Counted)
    specs = fleet_specs(get_preset("libero"), "half-fast", 12)
    sched = make_scheduler_config(scheduler).build(load_profile("l40s-pi05"), 3)
    net = LogNormalDelay(0.03, 0.8)
    result = FleetSimulator(specs, sched, 20.0, net, net, seed=5).run()
    assert len(made) == 12 and sum(r.chunks_received for r in result.robots) > 100
    assert [m.clamped_indices for m in made] == [0] * 12


# ------------------------------------------------------------------------------------------
# episode boundaries (a robot's world was reset)


class TestEpisodes:
    def test_a_boundary_voids_the_queue_and_makes_the_robot_useful_before_h_min(self):
        m = mirror(fps=10.0, h_min=5, h_max=10)
        m.on_observation(0, 0.0, 0.0)
        chunk = served(m, 0.05)
        assert [c.chunk_id for c in m.queue] == [chunk.chunk_id] and chunk.episode == 0
        m.on_observation(2, 0.25, 0.25)  # two steps executed: not useful yet (h_min = 5)
        assert not m.is_useful()
        m.on_observation(2, 0.35, 0.35, episode=1)  # the world reset; the robot dropped its chunk
        assert m.episode == 1 and m.episodes_started == 1
        assert m.queue == [] and m.ran_out is None
        assert m.is_useful()  # served now, not 3 steps later (which a starved robot never reaches)
        assert m.deadline() <= 0.35 + 1e-9  # nothing held: it runs dry at once
        fresh = served(m, 0.4)
        assert fresh.episode == 1 and fresh.i_start == 2

    def test_without_a_boundary_a_held_robot_would_never_be_served_again(self):
        # The failure the boundary exists for: a robot that dropped its chunks but said nothing
        # is held at an index the mirror thinks it still covers, so h_min is never reached.
        m = mirror(fps=10.0, h_min=5, h_max=10)
        m.on_observation(0, 0.0, 0.0)
        served(m, 0.05)
        for k in range(1, 30):
            m.on_observation(2, 0.2 + 0.1 * k, 0.2 + 0.1 * k)
            assert not m.is_useful()

    def test_episode_going_backwards_is_refused(self):
        m = mirror()
        m.on_observation(0, 0.0, 0.0, episode=3)
        with pytest.raises(ValueError, match="episode went backwards"):
            m.on_observation(1, 0.1, 0.1, episode=2)
        with pytest.raises(ValueError, match="episode must be >= 0"):
            mirror().on_observation(0, 0.0, 0.0, episode=-1)

    def test_a_first_observation_of_a_later_episode_is_no_boundary(self):
        m = mirror()
        m.on_observation(0, 0.0, 0.0, episode=7)  # a robot reconnecting mid-run
        assert m.episode == 7 and m.episodes_started == 0 and m.is_useful()

    def test_a_reordered_observation_of_the_old_episode_is_dropped(self):
        m = mirror(fps=10.0, h_min=5)
        m.on_observation(0, 0.0, 0.0)
        m.on_observation(1, 0.2, 0.2, episode=1)
        assert m.on_observation(0, 0.1, 0.21, episode=0) is False  # older capture: out of order
        assert m.episode == 1

    def test_boundaries_every_tick_buy_at_most_one_chunk_per_h_min_ticks(self):
        # A robot claiming a new episode at every tick is served no more often than an honest
        # robot that executes h_min actions per chunk.
        fps, h_min = 10.0, 5
        m = mirror(fps=fps, h_min=h_min, h_max=10)
        m.on_observation(0, 0.0, 0.0)
        served(m, 0.0)
        served_at = []
        for k in range(1, 101):
            t = k / fps
            m.on_observation(0, t, t, episode=k)
            if m.is_useful():
                served(m, t)
                served_at.append(t)
        assert served_at, "a boundary must make the robot useful"
        gaps = [b - a for a, b in zip(served_at, served_at[1:])]
        assert min(gaps) >= h_min / fps - 1e-9
        assert len(served_at) <= 100 // h_min + 1
