"""The offline optimum, the deterministic episode driver, the Rollout scheduler, the frontier CLI."""

from __future__ import annotations

import json
import math
import random

import numpy as np
import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.latency import load_profile
from lerobot_armory.mirror import advance, reach
from lerobot_armory.schedulers import check_batch, make_scheduler_config, scheduler_names
from lerobot_armory.schedulers.rollout import RolloutConfig, RolloutScheduler, dry_tick, index_at, queue_of, tick_reaching
from lerobot_armory.sim import FleetSimulator, LogNormalDelay, fleet_specs, get_preset
from lerobot_armory.sim.frontier import main as frontier_main
from lerobot_armory.sim.optimal import Episode, ReplayScheduler, canonical, episode_for, play, solve

PROFILE = load_profile("l40s-pi05")
SCHEDULERS = ["rr", "edf", "lookahead", "rollout"]


def build(name: str, ep: Episode, **kwargs):
    return make_scheduler_config(name, **kwargs).build(PROFILE, ep.max_batch_size)


# ------------------------------------------------------------------------------------------
# Hand-checkable optima
#
# libero fast robots: fps 20 (ticks every 50 ms), h_max 6; d_infer 73 / 109.8 ms for b = 1 / 2;
# one-way delay 3.75 ms. The first observations (index 0) reach the server at 3.75 ms.


def test_one_robot_one_second_by_hand():
    # Served alone at 3.75 ms, its chunk is ready at 76.75 ms and lands at 80.5 ms: before tick 2
    # (100 ms), so ticks 0 and 1 starve. A new chunk every 73 ms from an observation at most 3
    # ticks old covers 6 steps, so it never starves again: 18 of 20 ticks -> 0.9 robot-s.
    ep = episode_for("libero", "one-fast", 1, 1.0)
    res = solve(ep)
    assert res.exact and res.value == pytest.approx(0.9) and res.upper_bound == pytest.approx(0.9)
    for name in SCHEDULERS:
        assert play(ep, build(name, ep)).weighted_executed_s == pytest.approx(0.9)


def test_two_robots_one_second_by_hand():
    # Both observations arrive at 3.75 ms. Together (109.8 ms) both chunks land at 117.3 ms:
    # 3 starved ticks each. One after the other: 2 ticks for the first, and the second (served at
    # 76.75 ms, still holding index 0) lands at 153.5 ms: 4 ticks. Either way 6 starved ticks
    # at least, and none afterwards (a batch of two every 110 ms keeps both fed):
    # 40 - 6 = 34 steps -> 1.7 robot-s.
    ep = episode_for("libero", "all-fast", 2, 1.0)
    res = solve(ep)
    assert res.exact and res.value == pytest.approx(1.7)
    assert play(ep, ReplayScheduler(res.plan, ep.max_batch_size)).weighted_executed_s == pytest.approx(1.7)


# ------------------------------------------------------------------------------------------
# The optimum bounds every scheduler, and its plan replays to its value


@pytest.mark.parametrize(
    "preset, mix, n, horizon",
    [("libero", "all-fast", 3, 1.0), ("libero", "one-fast", 4, 1.5), ("piper", "half-fast", 4, 1.0), ("piper", "one-fast", 5, 1.0)],
)
def test_optimum_beats_every_scheduler_and_replays(preset, mix, n, horizon):
    ep = episode_for(preset, mix, n, horizon)
    values = {name: play(ep, build(name, ep)).weighted_executed_s for name in SCHEDULERS}
    res = solve(ep, max(values.values()))
    assert res.exact
    for name, v in values.items():
        assert v <= res.value + 1e-9, name
    assert res.plan is not None
    replayed = play(ep, ReplayScheduler(res.plan, ep.max_batch_size))
    assert replayed.weighted_executed_s == pytest.approx(res.value)
    assert replayed.batches[: len(res.plan)] == res.plan


def test_weighted_objective_and_warmup():
    # Fast robots weigh 3 (the objective follows the specs' weights); the first 0.5 s is EDF's.
    ep = episode_for("libero", "half-fast", 4, 1.0, fast_weight=3.0, warmup_s=0.5)
    assert ep.horizon_s == 1.5 and ep.warmup_s == 0.5
    edf = play(ep, build("edf", ep))
    assert edf.warmup_decisions > 0 and edf.warmup_weighted_s > 0
    assert all(t == 20 for t in edf.ticks)  # only the scored window's ticks count
    values = [play(ep, build(name, ep)).weighted_executed_s for name in SCHEDULERS]
    res = solve(ep, max(values))
    assert res.exact and res.value >= max(values) - 1e-9
    if res.plan is not None:
        assert play(ep, ReplayScheduler(res.plan, ep.max_batch_size)).weighted_executed_s == pytest.approx(res.value)


def test_budget_cut_gives_a_bound():
    ep = episode_for("libero", "all-fast", 4, 3.0)
    edf = play(ep, build("edf", ep))
    res = solve(ep, edf.weighted_executed_s, edf.batches, node_limit=200)
    assert not res.exact
    assert res.value >= edf.weighted_executed_s - 1e-9
    assert res.value <= res.upper_bound <= ep.max_weighted_s() + 1e-9
    assert 0 < res.gap < 1


def test_episode_validation():
    spec = fleet_specs(get_preset("libero"), "one-fast", 1)
    with pytest.raises(ConfigError) as info:
        Episode(tuple(spec), (0.073,), 0.0, 0.00375)
    assert info.value.field == "horizon_s"
    with pytest.raises(ConfigError) as info:
        Episode(tuple(spec), (0.073,), 1.0, 0.00375, phases_s=(0.2,))
    assert info.value.field == "phases_s"
    with pytest.raises(ConfigError) as info:
        Episode(tuple(spec), (0.073,), 1.0, 0.00375, warmup_s=1.0)
    assert info.value.field == "warmup_s"


# ------------------------------------------------------------------------------------------
# The deterministic driver is the simulator without jitter


@pytest.mark.parametrize("name", ["edf", "lookahead", "rollout"])
@pytest.mark.parametrize("preset, mix", [("libero", "half-fast"), ("piper", "one-fast")])
def test_play_matches_the_simulator_without_jitter(name, preset, mix):
    specs = fleet_specs(get_preset(preset), mix, 5, fast_weight=3.0)
    seed, duration = 3, 6.0
    rng = np.random.default_rng(seed)  # the simulator's first draws are the tick phases
    phases = tuple(rng.uniform(0.0, 1.0 / s.fps) for s in specs)
    cap = get_preset(preset).default_batch_cap(mix)
    ep = Episode(tuple(specs), tuple(PROFILE.table_s(cap)), duration, 0.00375, phases)
    mine = play(ep, build(name, ep))
    net = LogNormalDelay(0.00375, 0.0)
    sim = FleetSimulator(specs, make_scheduler_config(name).build(PROFILE, cap), duration, net, net, seed).run()
    assert [r.executed_steps for r in sim.robots] == mine.executed_steps
    assert [r.ticks for r in sim.robots] == mine.ticks


# ------------------------------------------------------------------------------------------
# The search's canonical queue and Rollout's queue form both agree with advance()


def realistic_chunks(rnd: random.Random, index: int) -> list[tuple[int, int, int]]:
    """Chunks a robot could hold: each starts at or before the index it has when it arrives."""
    chunks: list[tuple[int, int, int]] = []
    for _ in range(rnd.randint(0, 4)):
        arrival = rnd.randint(-3, 15)
        at = advance(index, sorted(chunks), arrival) if arrival > 0 else index
        start = rnd.randint(max(0, at - 8), at)
        chunks.append((start, start + rnd.randint(1, 10), arrival))
    return sorted(chunks)


def test_rollout_queue_agrees_with_advance():
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


def test_canonical_queue_keeps_advance():
    rnd = random.Random(3)
    for _ in range(3000):
        chunks = sorted(
            (s, s + rnd.randint(1, 9), rnd.randint(-2, 12)) for s in (rnd.randint(-3, 10) for _ in range(rnd.randint(0, 5)))
        )
        canon = canonical(chunks)
        assert list(canon) == sorted(canon)
        for ticks in range(0, 20):
            assert advance(0, canon, ticks) == advance(0, chunks, ticks)


# ------------------------------------------------------------------------------------------
# Rollout: registered, validated, deterministic, within the batch contract


def test_rollout_is_registered_and_validates():
    assert "rollout" in scheduler_names()
    cfg = make_scheduler_config("rollout", window_s=0.8, tail="due", candidates=2)
    assert isinstance(cfg, RolloutConfig) and cfg.type == "rollout"
    sched = cfg.build(PROFILE, 3)
    assert isinstance(sched, RolloutScheduler) and (sched.window_s, sched.tail, sched.candidates) == (0.8, "due", 2)
    bad = [({"window_s": 0}, "scheduler.window_s"), ({"tail": "x"}, "scheduler.tail"), ({"candidates": 0}, "scheduler.candidates")]
    for kwargs, field in [*bad, ({"order": "x"}, "scheduler.order")]:
        with pytest.raises(ConfigError) as info:
            make_scheduler_config("rollout", **kwargs).build(PROFILE, 3)
        assert info.value.field == field


@pytest.mark.parametrize(
    "preset, mix, n, knobs",
    [
        ("libero", "one-fast", 10, {}),
        ("piper", "half-fast", 6, {}),
        ("libero", "all-fast", 3, {}),
        ("piper", "one-fast", 10, {"order": "gain"}),
        ("piper", "one-fast", 10, {"keep_plan": True}),
    ],
)
def test_rollout_contract_and_determinism(preset, mix, n, knobs):
    specs = fleet_specs(get_preset(preset), mix, n, fast_weight=2.0)
    cap = get_preset(preset).default_batch_cap(mix)
    net = LogNormalDelay(0.00375, 0.3)
    runs = []
    for _ in range(2):
        sched = make_scheduler_config("rollout", **knobs).build(PROFILE, cap)
        # FleetSimulator calls check_batch on every decision (non-empty, <= cap, distinct, useful).
        res = FleetSimulator(specs, sched, 8.0, net, net, seed=1).run()
        runs.append(([r.executed_steps for r in res.robots], dict(res.batch_sizes)))
        assert set(res.batch_sizes) <= set(range(1, cap + 1))
    assert runs[0] == runs[1]


def test_rollout_gain_order_ranks_by_weighted_coverage_gain():
    """libero timing at t = 0, b = 3: a full batch lands at 142.4 + 3.75 ms; a chunk covers until
    h / fps - 3.75 ms (slow 0.5 s, fast 0.3 s). EDF serves the robot dry longest first; ``gain``
    serves the one whose queue a new chunk extends most, weighted, and a robot whose queue already
    reaches past the new chunk's end last."""
    from types import SimpleNamespace

    def robot(k: int, h: int, dry: float, weight: float = 1.0):
        return SimpleNamespace(
            k=k, i=k, h=h, fps=20.0, weight=weight, one_way=0.00375, span=h / 20.0 - 0.00375, deadline=dry, ready=-1.0
        )

    def ranked(order: str, robots) -> list[int]:
        sched = RolloutScheduler(PROFILE, 3, order=order)
        sched._order = sorted(robots, key=lambda r: (r.deadline, r.k))
        by_i = sorted(robots, key=lambda r: r.i)
        return [r.k for r in sched._useful_at(0.0, [r.ready for r in by_i], [r.deadline for r in by_i])]

    # gains: slow 0.5 - 0.00375 - 0.14615 = 0.35 s; fast 0.3 - 0.15 = 0.15 s (x3 = 0.45 s); covered: 0
    fleet = [robot(0, 6, -0.2), robot(1, 10, -0.1), robot(2, 10, 0.6)]
    assert ranked("deadline", fleet) == [0, 1, 2]
    assert ranked("gain", fleet) == [1, 0, 2]
    fleet[0] = robot(0, 6, -0.2, weight=3.0)
    assert ranked("gain", fleet) == [0, 1, 2]


@pytest.mark.parametrize("preset, mix, n", [("piper", "all-fast", 6), ("libero", "half-fast", 5)])
def test_rollout_kept_plan_only_overrides_when_it_scores_as_well(preset, mix, n):
    """A shadow scheduler without a kept plan decides on every same state: the two differ only at
    decisions the kept plan won (counted in ``plans_kept``), and that happens."""
    ep = episode_for(preset, mix, n, 3.0, fast_weight=3.0)
    plain = build("rollout", ep)
    keeper = build("rollout", ep, keep_plan=True)
    differ = []

    class Shadowed(RolloutScheduler):
        def select(self, robots, now):
            before = keeper.plans_kept
            fresh = plain.select(robots, now)
            picked = keeper.select(robots, now)
            if picked != fresh:
                differ.append(keeper.plans_kept - before)
            return picked

    play(ep, Shadowed(PROFILE, ep.max_batch_size))
    assert differ, "the kept plan never changed a decision"
    assert differ == [1] * len(differ)
    assert keeper.plans_kept == len(differ)


def test_rollout_kept_plan_skips_robots_that_left():
    ep = episode_for("libero", "half-fast", 4, 1.0)
    keeper = build("rollout", ep, keep_plan=True)
    seen: list[int] = []
    named: list[bool] = []  # whether the plan kept at each decision named the robot that left

    class Shrinking(RolloutScheduler):
        def select(self, robots, now):
            # Robot 0 leaves after the first decision: the kept plan may name it, it must not
            # come back in a batch.
            present = robots if not seen else robots[1:]
            named.append(any(ep.specs[0].robot_id in ids for ids in keeper._plan))
            batch = keeper.select(present, now)
            assert all(any(r is p for p in present) for r in batch)
            seen.append(len(batch))
            return batch

    play(ep, Shrinking(PROFILE, ep.max_batch_size))
    assert len(seen) > 3
    assert any(named[1:]), "the kept plan never named the robot that left: the test shows nothing"


def test_rollout_select_is_repeatable_on_one_state():
    ep = episode_for("piper", "half-fast", 6, 2.0)
    sched = build("rollout", ep)
    picks = []

    class Spy(RolloutScheduler):
        def select(self, robots, now):
            a = sched.select(robots, now)
            b = sched.select(robots, now)
            assert a == b
            check_batch(a, ep.max_batch_size, "rollout")
            picks.append(len(a))
            return a

    play(ep, Spy(PROFILE, ep.max_batch_size))
    assert picks and max(picks) <= ep.max_batch_size


# ------------------------------------------------------------------------------------------
# The command


def test_frontier_quick_profile_writes_everything(tmp_path, capsys):
    frontier_main([f"--out_dir={tmp_path}", "--profile=quick", "--workers=1", "--parts=optimum,pareto"])
    for name in ("fraction_of_optimum.csv", "fraction_of_optimum.md", "pareto.csv", "pareto.png", "n10_comparison.md", "COMMAND.md"):
        assert (tmp_path / name).is_file(), name
    rows = (tmp_path / "fraction_of_optimum.csv").read_text().splitlines()
    assert rows[0].startswith("preset,mix,robots,horizon_s,exact")
    search = json.loads((tmp_path / "optimum_search.json").read_text())
    for r in search:
        assert r["exact"]
        for label, value in r["values"].items():
            assert value <= r["optimum"] + 1e-9, label
    assert "fraction of the optimum" in capsys.readouterr().out


def test_frontier_rejects_bad_options(tmp_path):
    with pytest.raises(SystemExit) as info:
        frontier_main([f"--out_dir={tmp_path}", "--profile=nope"])
    assert info.value.code == 2
    with pytest.raises(SystemExit) as info:
        frontier_main([f"--out_dir={tmp_path}", "--parts=nope"])
    assert info.value.code == 2


def test_frontier_brackets_the_full_horizon_with_both_lagrangian_bounds(monkeypatch):
    # A search budget far too small for an overloaded fleet: the row must carry the bracket,
    # best found <= every bound, the bracket's upper end the tightest of the three, and every
    # scheduler's value inside it.
    from dataclasses import replace

    from lerobot_armory.sim import frontier

    tiny = replace(frontier.PROFILES["quick"], horizon_s=1.0, ladder_s=(), first_budget_s=0.001, lagrangian=True)
    monkeypatch.setitem(frontier.PROFILES, "tiny", tiny)
    row = frontier.optimum_job({"profile": "tiny", "preset": "libero", "mix": "all-fast", "robots": 4})
    lo, hi = row["bracket_lower"], row["bracket_upper"]
    assert hi == min(row["bracket_bb_upper"], row["bracket_lagrangian_upper"], row["bracket_time_priced_upper"])
    assert row["bracket_time_priced_upper"] <= row["bracket_lagrangian_upper"] + 1e-12
    assert lo <= hi
    assert all(v <= hi + 1e-9 for v in row["bracket_values"].values())
    md = frontier.optimum_markdown([row], list(row["values"]))
    assert "slot-price bound" in md and f"{row['bracket_time_priced_upper']:.2f}" in md


def test_told_the_end_windowed_schedulers_clip_their_window():
    """Off (inf) by default, so live decisions never see it; ``play(tell_end=True)`` sets it.
    Told the end of a 1 s cold-start episode, Rollout stops trading the last ticks for ones past
    the end: in piper half-fast N=6 it goes from 93.5 % of the optimum to 97.8 %, and Lookahead
    (which scores a window too) from 90.6 % to 95.7 %. EDF does not look ahead: unchanged."""
    ep = episode_for("piper", "half-fast", 6, 1.0)
    for name in ("rollout", "lookahead", "edf", "rr"):
        assert build(name, ep).episode_end_s == math.inf
    told = build("rollout", ep)
    registered, ended = play(ep, build("rollout", ep)), play(ep, told, tell_end=True)
    assert told.episode_end_s == ep.horizon_s
    result = solve(ep)
    assert result.exact
    optimum = result.value
    assert registered.weighted_executed_s < ended.weighted_executed_s <= optimum + 1e-9
    assert ended.weighted_executed_s >= 0.95 * optimum
    la, la_told = play(ep, build("lookahead", ep)), play(ep, build("lookahead", ep), tell_end=True)
    assert la.weighted_executed_s < la_told.weighted_executed_s <= optimum + 1e-9
    assert play(ep, build("edf", ep), tell_end=True).batches == play(ep, build("edf", ep)).batches


def test_rollout_same_tail_told_the_end_reaches_95_percent_where_the_default_misses():
    """The frontier setting (``tail=same``, told the episode's end like the optimum) on the
    committed row where the registered Rollout was furthest from the optimum (libero all-fast
    N=5, 1 s: 89.6 %). Its optimum is solved here, not read from the committed table."""
    ep = episode_for("libero", "all-fast", 5, 1.0)
    result = solve(ep, time_limit_s=120)
    assert result.exact
    plain = play(ep, build("rollout", ep)).weighted_executed_s
    same = play(ep, build("rollout", ep, tail="same"), tell_end=True).weighted_executed_s
    assert plain < 0.95 * result.value <= same <= result.value + 1e-9
