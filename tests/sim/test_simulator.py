"""The fleet simulator: determinism, hand-checkable runs, record schema, scheduler effects."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import load_profile
from lerobot_armory.schedulers import make_scheduler_config
from lerobot_armory.sim import MIXES, PRESETS, FleetSimulator, LogNormalDelay, fleet_specs, get_preset
from lerobot_armory.sim.presets import fast_count
from lerobot_armory.sim.run import SimConfig, run_label, simulate, table

TIMING_KEYS = {"wall_s", "decision_ms_p50", "decision_ms_p99", "decision_cpu_ms_p50", "decision_cpu_ms_p99"}


def config(scheduler="lookahead", **kwargs) -> SimConfig:
    sched_kwargs = kwargs.pop("sched", {})
    kwargs.setdefault("duration_s", 10.0)
    return SimConfig(scheduler=make_scheduler_config(scheduler, **sched_kwargs), **kwargs).resolved()


def strip_timing(record: dict) -> dict:
    return {k: v for k, v in record.items() if k not in TIMING_KEYS}


# ------------------------------------------------------------------------------------------
# Presets, mixes, network


def test_presets_match_spec():
    lib, pip = get_preset("libero"), get_preset("piper")
    assert (lib.chunk_size, lib.fps, lib.h_min, lib.fast_h_max, lib.slow_h_max) == (10, 20.0, 1, 6, 10)
    assert lib.default_batch_cap("all-fast") == lib.default_batch_cap("one-fast") == 3
    assert (pip.chunk_size, pip.fps, pip.h_min, pip.fast_h_max, pip.slow_h_max) == (20, 30.0, 5, 10, 20)
    assert pip.default_batch_cap("all-fast") == 3
    assert pip.default_batch_cap("one-fast") == pip.default_batch_cap("half-fast") == 5
    # Server round trip 5-10 ms: a one-way median inside 2.5-5 ms.
    assert 2.5 <= lib.net_median_ms <= 5.0
    with pytest.raises(ConfigError) as info:
        get_preset("nope")
    assert info.value.field == "preset"


@pytest.mark.parametrize(
    "mix, n, fast", [("all-fast", 4, 4), ("one-fast", 10, 1), ("half-fast", 10, 5), ("half-fast", 5, 2), ("half-fast", 1, 1)]
)
def test_fleet_specs(mix, n, fast):
    specs = fleet_specs(get_preset("piper"), mix, n, fast_weight=3.0)
    assert len(specs) == n
    assert fast_count(mix, n) == fast
    assert [s.tier for s in specs] == ["fast"] * fast + ["slow"] * (n - fast)
    for s in specs:
        assert s.h_max == (10 if s.tier == "fast" else 20)
        assert s.weight == (3.0 if s.tier == "fast" else 1.0)
        assert (s.fps, s.chunk_size, s.h_min) == (30.0, 20, 5)
    assert len({s.robot_id for s in specs}) == n


@pytest.mark.parametrize(
    "args, field",
    [(("nope", 3, 1.0), "mix"), (("one-fast", 0, 1.0), "robots"), (("one-fast", 3, 0.0), "fast_weight")],
)
def test_fleet_specs_errors(args, field):
    with pytest.raises(ConfigError) as info:
        fleet_specs(get_preset("libero"), *args)
    assert info.value.field == field


def test_lognormal_delay():
    rng = np.random.default_rng(0)
    assert LogNormalDelay(0.05, 0.0).sample(rng) == 0.05
    assert np.all(LogNormalDelay(0.05, 0.0).sample(rng, 10) == 0.05)
    draws = LogNormalDelay(0.05, 0.5).sample(rng, 20000)
    assert np.median(draws) == pytest.approx(0.05, rel=0.03)
    assert np.std(np.log(draws)) == pytest.approx(0.5, rel=0.03)
    assert LogNormalDelay(0.05, 0.5).mean_s == pytest.approx(0.05 * math.exp(0.125))
    with pytest.raises(ConfigError) as info:
        LogNormalDelay(-0.01, 0.1)
    assert info.value.field == "net_median_ms"
    with pytest.raises(ConfigError) as info:
        LogNormalDelay(0.01, -0.1)
    assert info.value.field == "net_sigma"


def test_resolved_fills_preset_defaults():
    cfg = config(preset="piper", mix="half-fast", robots=4)
    assert cfg.max_batch_size == 5
    assert cfg.latency_profile == "l40s-pi05"
    assert cfg.net_median_ms == 3.75 and cfg.net_sigma == 0.2
    assert config(preset="piper", mix="all-fast", robots=4).max_batch_size == 3
    explicit = config(max_batch_size=2, latency_profile="h100-pi05", net_median_ms=50.0, net_sigma=0.0)
    assert (explicit.max_batch_size, explicit.latency_profile, explicit.net_median_ms, explicit.net_sigma) == (
        2,
        "h100-pi05",
        50.0,
        0.0,
    )


def test_simulator_rejects_bad_fleets():
    sched = make_scheduler_config("rr").build(load_profile("l40s-pi05"), 3)
    net = LogNormalDelay(0.01, 0.0)
    specs = fleet_specs(get_preset("libero"), "one-fast", 2)
    for bad_specs, duration, field in [([], 1.0, "robots"), (specs, 0.0, "duration_s"), ([specs[0], specs[0]], 1.0, "robots")]:
        with pytest.raises(ConfigError) as info:
            FleetSimulator(bad_specs, sched, duration, net, net)
        assert info.value.field == field


# ------------------------------------------------------------------------------------------
# Determinism


@pytest.mark.parametrize("scheduler", ["rr", "edf", "lookahead"])
def test_same_seed_same_record(scheduler):
    cfg = config(scheduler, mix="half-fast", robots=6, net_median_ms=20.0, net_sigma=0.5)
    a, b = simulate(cfg, 7), simulate(cfg, 7)
    assert strip_timing(a) == strip_timing(b)
    assert a["seed"] == 7


def test_different_seeds_differ():
    cfg = config("edf", mix="half-fast", robots=6, net_median_ms=20.0, net_sigma=0.5)
    a, b = simulate(cfg, 1), simulate(cfg, 2)
    assert a["per_robot"] != b["per_robot"]
    assert a["first_executed_index"] != b["first_executed_index"]


# ------------------------------------------------------------------------------------------
# A robot alone on a jitter-free network, computed by hand
#
# libero fast robot: fps 20, h_max 6, h_min 1; d_infer(1) = 73 ms; one-way delay 3.75 ms.
# Tick k happens at phase + k/20. The first observation (index 0) reaches the server at
# phase + 3.75 ms; its chunk is ready at phase + 76.75 ms and reaches the robot at phase + 80.5 ms,
# i.e. before tick 2 (phase + 100 ms): ticks 0 and 1 starve. The observations of ticks 1 and 2
# still carry index 0 (same as served: not useful); tick 3's (index 1) is served at
# phase + 153.75 ms. From then on every chunk is ready 73 ms after the previous one with an
# observation at most 3 ticks old and 6 steps long, so the robot never starves again.
# 10 s = 200 ticks -> 2 starved ticks; 1 + 135 dispatches (phase + 153.75 ms + 134 * 73 ms <
# 10 s); the last one reaches the robot after the end: 135 chunks received.


@pytest.mark.parametrize("scheduler", ["rr", "edf", "lookahead"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_single_robot_by_hand(scheduler, seed):
    specs = fleet_specs(get_preset("libero"), "one-fast", 1)
    sched = make_scheduler_config(scheduler).build(load_profile("l40s-pi05"), 3)
    net = LogNormalDelay(0.00375, 0.0)
    result = FleetSimulator(specs, sched, 10.0, net, net, seed).run()
    (robot,) = result.robots
    assert robot.ticks == 200
    assert robot.starved_steps == 2
    assert robot.executed_steps == 198
    assert robot.starvation_pct == pytest.approx(1.0)
    assert robot.executed_s == pytest.approx(198 / 20)
    assert dict(result.batch_sizes) == {1: 136}
    assert robot.chunks_received == 135
    assert robot.first_executed_index["0"] == 1  # the first chunk starts at its own index
    assert sum(robot.first_executed_index.values()) == 135
    assert all(k != "unused" and 0 <= int(k) < 6 for k in robot.first_executed_index)
    assert result.mirror_index_error and set(result.mirror_index_error) == {0}


@pytest.mark.parametrize("preset", sorted(PRESETS))
@pytest.mark.parametrize("scheduler", ["rr", "edf", "lookahead"])
def test_mirror_is_exact_without_jitter(preset, scheduler):
    rec = simulate(config(scheduler, preset=preset, mix="half-fast", robots=6, net_median_ms=40.0, net_sigma=0.0), 0)
    assert rec["mirror_index_error_p99"] == 0.0


def test_mirror_stays_close_with_jitter():
    rec = simulate(config("edf", mix="half-fast", robots=6), 0)  # preset jitter (sigma 0.2)
    assert rec["mirror_index_error_p99"] <= 1.0


# ------------------------------------------------------------------------------------------
# Record invariants over presets, mixes and schedulers


@pytest.mark.parametrize("preset", sorted(PRESETS))
@pytest.mark.parametrize("mix", MIXES)
@pytest.mark.parametrize("scheduler", ["rr", "edf", "lookahead"])
def test_every_scheduler_on_every_preset_and_mix(preset, mix, scheduler):
    cfg = config(scheduler, preset=preset, mix=mix, robots=5, duration_s=8.0)
    fps = PRESETS[preset].fps
    specs = fleet_specs(PRESETS[preset], mix, 5)
    sched = cfg.scheduler.build(load_profile(cfg.latency_profile), cfg.max_batch_size)
    net = cfg.network()
    result = FleetSimulator(specs, sched, cfg.duration_s, net, net, seed=4).run()

    for r, s in zip(result.robots, specs, strict=True):
        # The tick phase is in (0, 1/fps): exactly duration * fps ticks happen before the end.
        assert r.ticks == round(cfg.duration_s * fps)
        assert 0 < r.executed_steps <= r.ticks
        assert r.executed_steps + r.starved_steps == r.ticks
        assert r.starvation_pct == pytest.approx(100 * (r.ticks - r.executed_steps) / r.ticks)
        assert r.tier == s.tier and r.weight == s.weight
        assert sum(r.first_executed_index.values()) == r.chunks_received
        assert all(k == "unused" or 0 <= int(k) < s.h_max for k in r.first_executed_index)
    assert max(result.batch_sizes) <= cfg.max_batch_size
    assert min(result.batch_sizes) >= 1
    assert sum(result.batch_sizes.values()) == len(result.decision_s)
    # Every dispatched chunk is accounted for: received before the end or still in flight.
    served = sum(b * c for b, c in result.batch_sizes.items())
    received = sum(r.chunks_received for r in result.robots)
    assert served - 2 * cfg.max_batch_size <= received <= served

    rec = simulate(cfg, 4)
    assert strip_timing(rec)["per_robot"] == [
        {"robot_id": r.robot_id, "tier": r.tier, "starvation_pct": r.starvation_pct, "executed_s": r.executed_s}
        for r in result.robots
    ]
    expected_tiers = {t for t in ("fast", "slow") if any(s.tier == t for s in specs)}
    assert set(rec["tiers"]) == expected_tiers
    for tier, row in rec["tiers"].items():
        rows = [r for r in result.robots if r.tier == tier]
        assert row["robots"] == len(rows)
        assert row["starvation_pct"] == pytest.approx(np.mean([r.starvation_pct for r in rows]))
        assert row["executed_s"] == pytest.approx(sum(r.executed_s for r in rows))
    assert rec["avg_starvation_pct"] == pytest.approx(np.mean([r.starvation_pct for r in result.robots]))
    assert all(1 <= int(b) <= cfg.max_batch_size for b in rec["batch_sizes"])
    assert rec["executed_s"] == pytest.approx(sum(r.executed_s for r in result.robots))


def test_all_fast_record_has_only_the_fast_tier():
    rec = simulate(config("rr", mix="all-fast", robots=3), 0)
    assert list(rec["tiers"]) == ["fast"]
    assert rec["tiers"]["fast"]["robots"] == 3


@pytest.mark.parametrize("cap", [1, 2, 4, 7])
def test_batch_cap_is_respected_including_extrapolated_sizes(cap):
    for scheduler in ("rr", "edf", "lookahead"):
        rec = simulate(config(scheduler, mix="all-fast", robots=8, max_batch_size=cap, duration_s=5.0), 0)
        sizes = [int(b) for b in rec["batch_sizes"]]
        assert max(sizes) <= cap
        assert rec["latency_extrapolated"] == (cap > 5)


def test_batching_helps_an_overloaded_all_fast_fleet():
    """Cap 1 cannot keep 8 fast robots fed; a cap of 3 serves them much better."""
    one = simulate(config("edf", mix="all-fast", robots=8, max_batch_size=1, duration_s=10.0), 0)
    three = simulate(config("edf", mix="all-fast", robots=8, max_batch_size=3, duration_s=10.0), 0)
    assert three["avg_starvation_pct"] < one["avg_starvation_pct"] - 10


def test_lookahead_depth_two_runs():
    rec = simulate(config("lookahead", sched={"depth": 2}, mix="one-fast", robots=4, duration_s=5.0), 0)
    assert rec["depth"] == 2
    assert rec["label"] == "LA w=1 L=2"
    assert max(int(b) for b in rec["batch_sizes"]) <= 3


# ------------------------------------------------------------------------------------------
# Weights


def test_fast_weight_protects_the_fast_robot():
    """libero, one-fast, N=10, b=3: a heavier fast robot starves less, slow robots pay for it."""
    fast, slow = {}, {}
    for w in (1.0, 3.0, 5.0):
        recs = [simulate(config("lookahead", mix="one-fast", robots=10, fast_weight=w, duration_s=60.0), s) for s in (0, 1)]
        fast[w] = np.mean([r["tiers"]["fast"]["starvation_pct"] for r in recs])
        slow[w] = np.mean([r["tiers"]["slow"]["starvation_pct"] for r in recs])
        assert all(r["fast_weight"] == w and r["label"] == f"LA w={w:g}" for r in recs)
    assert fast[5.0] < fast[3.0] < fast[1.0]
    assert fast[5.0] < fast[1.0] - 20
    assert slow[5.0] > slow[1.0]


def test_fast_weight_changes_nothing_for_rr():
    a = simulate(config("rr", mix="one-fast", robots=6, fast_weight=1.0), 0)
    b = simulate(config("rr", mix="one-fast", robots=6, fast_weight=5.0), 0)
    assert a["per_robot"] == b["per_robot"]
    assert b["tiers"]["fast"]["executed_s"] == a["tiers"]["fast"]["executed_s"]
    assert b["weighted_executed_s"] == pytest.approx(
        a["weighted_executed_s"] + 4 * a["tiers"]["fast"]["executed_s"]
    )


# ------------------------------------------------------------------------------------------
# Labels and table


def test_run_labels():
    assert run_label("rr", 5.0) == "RR"
    assert run_label("edf", 1.0) == "EDF"
    assert run_label("lookahead", 3.0) == "LA w=3"
    assert run_label("lookahead", 1.5, depth=2) == "LA w=1.5 L=2"


def test_table_groups_seeds():
    cfg = config("edf", mix="half-fast", robots=4, duration_s=3.0)
    runs = [simulate(cfg, s) for s in (0, 1, 2)]
    text = table(runs)
    lines = text.splitlines()
    assert len(lines) == 3  # header, rule, one row for the three seeds
    row = lines[2].split()
    assert row[:4] == ["libero", "half-fast", "4", "3"]
    assert "EDF" in row and row[row.index("EDF") + 1] == "3"
    avg = np.mean([r["avg_starvation_pct"] for r in runs])
    assert f"{avg:.2f}" in lines[2]
