"""Latency profiles d_infer(b): built-in tables (docs/spec.md §5), extrapolation, JSON files, errors; the
online model that learns d_infer from served batches, unit-tested on hand-made sample streams and
end to end on a live server."""

from __future__ import annotations

import json
import statistics
import time

import numpy as np
import pytest
from prometheus_client import generate_latest

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import BUILTIN_PROFILES, LatencyProfile, OnlineLatency, load_profile, validate_latencies
from lerobot_armory.schedulers import EarliestDeadlineConfig
from lerobot_armory.entrypoints.server import ArmoryServer, ServerConfig, latency_learning
from lerobot_armory.engine.options import EngineOptions
from lerobot_armory.entrypoints.grpc.service import PolicyInfo
from lerobot_armory.engine.protocol import UnguidedEngine
from tests.support.pusher import Pusher

SPEC_TABLES = {
    "l40s-pi05": [73.0, 109.8, 142.4, 177.5, 211.1],
    "h100-pi05": [42.3, 56.0, 66.1, 79.3, 87.2],
    "l40s-groot": [71.8, 76.5, 83.5, 91.8, 100.9],
}


@pytest.mark.parametrize("name", sorted(SPEC_TABLES))
def test_builtin_profiles_match_spec(name):
    p = load_profile(name)
    assert p.name == name
    assert p.source == "builtin"
    assert list(p.latency_ms) == SPEC_TABLES[name]
    assert p.measured_sizes == 5
    for b, ms in enumerate(SPEC_TABLES[name], start=1):
        assert p.latency_ms_for(b) == ms
        assert p.latency_s(b) == pytest.approx(ms / 1000)
        assert not p.is_extrapolated(b)


# Our engine's own profiles: the latency_ms of the GPU results they were measured in.
MEASURED = {
    "h200-pi05-graphs": "h200_fused.json",
    "h200-pi0-graphs": "h200_pi0.json",
    "h200-smolvla-graphs": "h200_smolvla.json",
}


def test_builtin_names():
    assert set(BUILTIN_PROFILES) == set(SPEC_TABLES) | set(MEASURED)
    assert "H100" in load_profile("h100-pi05").device


@pytest.mark.parametrize("name", sorted(MEASURED))
def test_measured_profiles_are_the_committed_gpu_results(name):
    from pathlib import Path

    result = json.loads((Path(__file__).parents[2] / "docs/results/gpu" / MEASURED[name]).read_text())
    p = load_profile(name)
    assert list(p.latency_ms) == result["latency_ms"] and p.measured_sizes == 8
    assert result["device"] in p.device


def test_linear_extrapolation_beyond_the_table():
    p = load_profile("l40s-pi05")
    assert p.latency_ms_for(6) == pytest.approx(211.1 + 33.6)
    assert p.latency_ms_for(8) == pytest.approx(211.1 + 3 * 33.6)
    assert p.is_extrapolated(6) and p.is_extrapolated(10)
    assert not p.is_extrapolated(5)
    h = load_profile("h100-pi05")
    assert h.latency_ms_for(7) == pytest.approx(87.2 + 2 * 7.9)


def test_table_s_and_describe_mark_extrapolation():
    p = load_profile("l40s-groot")
    table = p.table_s(7)
    assert table[:5] == pytest.approx([0.0718, 0.0765, 0.0835, 0.0918, 0.1009])
    assert table[5] == pytest.approx((100.9 + 9.1) / 1000)
    assert table[6] == pytest.approx((100.9 + 2 * 9.1) / 1000)
    text = p.describe(7)
    lines = text.splitlines()
    assert len(lines) == 1 + 7
    assert sum("extrapolated" in line for line in lines) == 2
    assert "extrapolated" not in lines[5] and "extrapolated" in lines[6]


def test_single_point_profile_assumes_no_batching_gain():
    p = LatencyProfile("one", (10.0,))
    assert p.latency_ms_for(3) == pytest.approx(30.0)
    assert p.is_extrapolated(2)


def test_batch_size_below_one_is_rejected():
    with pytest.raises(ValueError):
        load_profile("l40s-pi05").latency_ms_for(0)


def write(tmp_path, data, name="profile.json"):
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return str(path)


def test_load_list_form(tmp_path):
    path = write(tmp_path, {"name": "my-gpu", "device": "H100", "latency_ms": [42.3, 56.0, 66.1]})
    p = load_profile(path)
    assert p.name == "my-gpu"
    assert p.device == "H100"
    assert p.latency_ms == (42.3, 56.0, 66.1)
    assert p.source == path
    assert p.latency_ms_for(4) == pytest.approx(66.1 + 10.1)


def test_load_dict_form_in_any_key_order(tmp_path):
    path = write(tmp_path, {"latency_ms": {"3": 30, "1": 10, "2": 20.5}}, name="gpu-x.json")
    p = load_profile(path)
    assert p.latency_ms == (10.0, 20.5, 30.0)
    assert p.name == "gpu-x"  # no name: the file stem
    assert p.device == ""


def test_integer_entries_are_accepted_and_equal_entries_allowed(tmp_path):
    p = load_profile(write(tmp_path, {"latency_ms": [50, 50, 60]}))
    assert p.latency_ms == (50.0, 50.0, 60.0)


def test_save_load_round_trip(tmp_path):
    original = LatencyProfile("rt", (12.5, 20.0, 26.25), device="my box", source="profiled")
    path = tmp_path / "sub.json"
    original.save(path)
    assert json.loads(path.read_text()) == {"name": "rt", "device": "my box", "latency_ms": [12.5, 20.0, 26.25]}
    loaded = load_profile(str(path))
    assert (loaded.name, loaded.latency_ms, loaded.device) == (original.name, original.latency_ms, original.device)
    assert loaded.source == str(path)


def test_builtin_round_trip(tmp_path):
    path = tmp_path / "h100.json"
    load_profile("h100-pi05").save(path)
    assert load_profile(str(path)).latency_ms == tuple(SPEC_TABLES["h100-pi05"])


def assert_profile_error(path_or_name):
    with pytest.raises(ConfigError) as info:
        load_profile(path_or_name)
    assert info.value.field == "latency_profile"
    assert str(info.value).startswith("latency_profile: ")
    return info.value


def test_unknown_name():
    err = assert_profile_error("a100-pi05")
    assert "l40s-pi05" in err.message  # lists what would be accepted


def test_missing_file(tmp_path):
    assert_profile_error(str(tmp_path / "nonexistent.json"))
    assert_profile_error("/nonexistent.json")


def test_directory_is_not_a_profile(tmp_path):
    assert_profile_error(str(tmp_path))


@pytest.mark.parametrize(
    "content",
    [
        '{"latency_ms": [1, 2',  # malformed JSON
        "",  # empty file
        "[1, 2, 3]",  # not an object
        '{"latency": [1, 2]}',  # no latency_ms
        '{"latency_ms": "fast"}',  # neither list nor object
        '{"latency_ms": []}',  # empty table
        '{"latency_ms": [5, 4]}',  # decreasing
        '{"latency_ms": [10, 20, 15, 30]}',  # decreasing in the middle
        '{"latency_ms": [0, 1]}',  # non-positive
        '{"latency_ms": [-3]}',
        '{"latency_ms": [1, "a"]}',  # non-numeric
        '{"latency_ms": [1, null]}',
        '{"latency_ms": [1, true]}',
        '{"latency_ms": [1, NaN]}',
        '{"latency_ms": [1, Infinity]}',
        '{"latency_ms": {"1": 10, "3": 30}}',  # gap in batch sizes
        '{"latency_ms": {"2": 10, "3": 30}}',  # does not start at 1
        '{"latency_ms": {"one": 10}}',  # key not a batch size
        '{"latency_ms": {"1": 10, "2": 5}}',  # decreasing, dict form
        '{"latency_ms": {"1": 10, "2": "x"}}',  # non-numeric, dict form
    ],
)
def test_bad_files(tmp_path, content):
    assert_profile_error(write(tmp_path, content))


def test_non_utf8_file(tmp_path):
    path = tmp_path / "bin.json"
    path.write_bytes(b"\xff\xfe\x00garbage")
    assert_profile_error(str(path))


def test_dict_keys_with_leading_zero(tmp_path):
    path = write(tmp_path, {"latency_ms": {"01": 42.3, "02": 56.0}})
    try:
        p = load_profile(path)
    except ConfigError:
        return  # a clean ConfigError would also be acceptable
    assert p.latency_ms == (42.3, 56.0)


@pytest.mark.parametrize("values", [(), (0.0,), (-1.0, 2.0), (10.0, 9.0), (float("nan"),)])
def test_profile_object_validates_itself(values):
    with pytest.raises(ConfigError) as info:
        LatencyProfile("x", values)
    assert info.value.field == "latency_profile"


# ---- OnlineLatency: d_infer learnt from served batches ----------------------------------------


def true_ms(b: int) -> float:
    """The machine the streams below describe: 20 ms + 5 ms per robot."""
    return 20.0 + 5.0 * b


def feed(model: OnlineLatency, sizes, rounds: int, ms=true_ms, jitter=(0.0,)) -> None:
    """``rounds`` batches of every size in ``sizes``, each taking ``ms(b)`` plus a cycling jitter."""
    k = 0
    for _ in range(rounds):
        for b in sizes:
            model.observe(b, (ms(b) + jitter[k % len(jitter)]) / 1000.0)
            k += 1


WRONG = LatencyProfile("wrong", (100.0, 200.0, 300.0, 400.0))


def test_online_latency_starts_at_the_profile():
    m = OnlineLatency(WRONG, 5)
    assert m.table_ms() == (100.0, 200.0, 300.0, 400.0, 500.0)  # b=5 extrapolated like the profile
    assert m.table_s() == pytest.approx([0.1, 0.2, 0.3, 0.4, 0.5])
    assert all(d.pct == 0.0 and not d.measured and d.samples == 0 for d in m.drift())
    assert m.observed == 0


def test_online_latency_converges_from_a_wrong_startup_table():
    m = OnlineLatency(WRONG, 4)
    feed(m, [1, 2, 3, 4], rounds=10, jitter=(0.0, 1.5, -1.0, 0.5, -0.5))
    assert m.table_ms() == pytest.approx([true_ms(b) for b in range(1, 5)], abs=1.0)
    drift = m.drift()
    assert all(d.measured and d.samples == 10 for d in drift)
    assert drift[0].pct == pytest.approx(-75.0, abs=1.0)
    worst = m.max_drift()
    assert worst.batch_size == 4 and worst.pct == pytest.approx(-90.0, abs=0.5)


def test_the_median_takes_over_after_min_samples():
    m = OnlineLatency(WRONG, 2, min_samples=3)
    assert not m.observe(1, 0.025) and not m.observe(1, 0.025)  # two samples: still the profile
    assert m.table_ms() == (100.0, 200.0)
    assert m.observe(1, 0.025)  # the third publishes; b=2 rescaled from the profile's shape
    assert m.table_ms() == pytest.approx((25.0, 50.0))


def test_an_outlier_burst_does_not_move_the_table():
    m = OnlineLatency(WRONG, 3, confirm=5)
    feed(m, [1, 2, 3], rounds=10)
    before = m.table_ms()
    # A hiccup every few batches, and a burst of four 10x batches in a row: all held aside.
    for k in range(40):
        m.observe(2, 10 * true_ms(2) / 1000 if k % 7 == 3 else true_ms(2) / 1000)
    for _ in range(4):
        assert not m.observe(2, 10 * true_ms(2) / 1000)
        assert not m.observe(1, true_ms(1) / 1000 / 10)  # too fast is as suspect as too slow
    assert m.table_ms() == before
    assert m.rejected == 6 + 8


def test_a_step_change_is_followed_within_bounded_batches():
    m = OnlineLatency(WRONG, 3, window=21, confirm=5)
    feed(m, [1, 2, 3], rounds=21)
    # The machine becomes 5x slower: held aside as outliers until `confirm` in a row agree.
    for k in range(1, 6):
        changed = m.observe(3, 5 * true_ms(3) / 1000)
        assert changed == (k == 5)
    assert m.table_ms()[2] == pytest.approx(5 * true_ms(3))
    # A milder change (1.5x, inside the outlier factor) moves the median after window // 2 + 1.
    m2 = OnlineLatency(WRONG, 3, window=21)
    feed(m2, [1, 2, 3], rounds=21)
    slower = lambda b: 1.5 * true_ms(b)  # noqa: E731
    feed(m2, [1, 2, 3], rounds=10, ms=slower)
    assert m2.table_ms()[0] == pytest.approx(true_ms(1))
    feed(m2, [1, 2, 3], rounds=1, ms=slower)
    assert m2.table_ms() == pytest.approx([slower(b) for b in (1, 2, 3)])


def test_unseen_sizes_are_extrapolated_from_the_seen_ones():
    # Two sizes seen: a line through them for the rest.
    m = OnlineLatency(WRONG, 6)
    feed(m, [1, 2], rounds=5)
    assert m.table_ms() == pytest.approx([true_ms(b) for b in range(1, 7)])
    assert [d.measured for d in m.drift()] == [True, True, False, False, False, False]
    # One size seen: the start-up profile's shape, rescaled to it.
    m = OnlineLatency(LatencyProfile("shape", (40.0, 50.0, 60.0)), 3)
    feed(m, [3], rounds=5, ms=lambda b: 30.0)
    assert m.table_ms() == pytest.approx([20.0, 25.0, 30.0])
    # Sizes 2 and 4 seen: 3 sits on the line between them, 1 on its extension.
    m = OnlineLatency(WRONG, 4)
    feed(m, [2, 4], rounds=5)
    assert m.table_ms() == pytest.approx([true_ms(b) for b in range(1, 5)])


def test_the_line_is_robust_to_one_bad_size():
    m = OnlineLatency(WRONG, 7)
    feed(m, [1, 2, 3, 4, 5], rounds=5, ms=lambda b: 10.0 if b == 1 else true_ms(b))  # b=1 odd on this machine
    # Theil-Sen (median of pairwise slopes) keeps the trend of b = 2..5; least squares would not.
    assert m.table_ms()[5:] == pytest.approx((true_ms(6), true_ms(7)))


def test_the_table_stays_positive_and_non_decreasing():
    # Medians that decrease with b are raised to their predecessor (as start-up profiling does).
    m = OnlineLatency(WRONG, 3)
    feed(m, [1, 2, 3], rounds=5, ms=lambda b: {1: 50.0, 2: 40.0, 3: 60.0}[b])
    assert m.table_ms() == pytest.approx([50.0, 50.0, 60.0])
    # A steep line through b=3, 4 would go negative at b=1: floored at d(3) * b / 3.
    m = OnlineLatency(WRONG, 4)
    feed(m, [3, 4], rounds=5, ms=lambda b: {3: 10.0, 4: 100.0}[b])
    assert m.table_ms() == pytest.approx([10 / 3, 20 / 3, 10.0, 100.0])
    # Any stream: every published table is a valid profile.
    m = OnlineLatency(WRONG, 4, tolerance=0.0)
    for k in range(400):
        b = 1 + (k * 7) % 4
        ms = (5.0 + 37.0 * ((k * 13) % 11)) * (1 + b % 3)  # scrambled, non-monotone in b
        m.observe(b, ms / 1000)
        validate_latencies(m.table_ms(), "online")


def test_small_changes_are_not_published():
    m = OnlineLatency(WRONG, 1, tolerance=0.02)
    feed(m, [1], rounds=3)
    assert m.table_ms() == (25.0,)
    assert not m.observe(1, 0.0254) and not m.observe(1, 0.0254)  # median 25.2: inside 2 %
    assert m.table_ms() == (25.0,)
    assert not m.observe(1, 0.0)  # nonsense times are ignored
    assert not m.observe(1, float("nan"))
    assert m.observed == 5


def test_a_size_not_served_for_long_is_refitted_and_restarts():
    m = OnlineLatency(WRONG, 2, stale_after=50)
    feed(m, [1, 2], rounds=5)
    feed(m, [2], rounds=60, ms=lambda b: 2 * true_ms(b))  # b=1 not served for 60 batches; machine slower
    d1 = m.drift()[0]
    assert not d1.measured
    assert d1.current_ms == pytest.approx(2 * true_ms(2) * 100 / 200)  # the profile's shape, rescaled
    m.observe(1, 2 * true_ms(1) / 1000)  # back: its old samples are dropped, not mixed in
    assert m.drift()[0].samples == 1


def test_online_latency_is_deterministic():
    tables = []
    for _ in range(2):
        m = OnlineLatency(WRONG, 4)
        out = []
        for k in range(300):
            m.observe(1 + k % 4, (20 + 5 * (k % 4) + (k * 31) % 17) / 1000)
            out.append(m.table_ms())
        tables.append(out)
    assert tables[0] == tables[1]


def test_online_latency_rejects_bad_arguments():
    m = OnlineLatency(WRONG, 3)
    with pytest.raises(ValueError):
        m.observe(0, 0.01)
    with pytest.raises(ValueError):
        m.observe(4, 0.01)
    with pytest.raises(ValueError):
        OnlineLatency(WRONG, 0)
    with pytest.raises(ValueError):
        OnlineLatency(WRONG, 3, min_samples=6, confirm=5)
    with pytest.raises(ValueError):
        OnlineLatency(WRONG, 3, outlier_factor=1.0)


# ---- the live server: learning on by default for a profiled table, off when pinned ----------


def learning_decision(profile_source: str, **cfg):
    emulate = cfg.pop("emulate", None)
    config = ServerConfig(engine=EngineOptions(emulate_profile=emulate), **cfg)
    return latency_learning(config, LatencyProfile("p", (10.0,), source=profile_source))


def test_which_tables_learn():
    assert learning_decision("profiled")[0] is True  # profiled at start-up (saved to a path or not)
    assert learning_decision("profiled", latency_profile="new.json")[0] is True
    learn, why = learning_decision("builtin", latency_profile="h100-pi05")
    assert learn is False and "pinned" in why  # the user chose the table
    assert learning_decision("builtin", emulate="h100-pi05")[0] is False  # batches take the profile
    assert learning_decision("builtin", latency_profile="h100-pi05", latency_learning=True)[0] is True
    assert learning_decision("profiled", latency_learning=False)[0] is False


class TimedEngine(UnguidedEngine):
    """Batches take a known time (base + per robot), chunks are zeros of the policy's shape."""

    def __init__(self, horizon: int, action_dim: int, base_s: float = 0.020, per_robot_s: float = 0.005) -> None:
        self.horizon, self.action_dim, self.base_s, self.per_robot_s = horizon, action_dim, base_s, per_robot_s

    def infer(self, observations, tasks, noise_seeds=None, history=None):
        time.sleep(self.base_s + self.per_robot_s * len(observations))
        return np.zeros((len(observations), self.horizon, self.action_dim), np.float32)


def serve_for(engine, profile: LatencyProfile, learn: bool, seconds: float = 3.0):
    """A real server with a timed engine, four pushing robots for ``seconds``; returns the server (stopped)."""
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    timed = TimedEngine(engine.chunk_size, len(engine.action_names))
    server = ArmoryServer(timed, info, profile, EarliestDeadlineConfig(), 3, port=0, learn_latency=learn).start()
    robots = []
    try:
        # Different periods so that batches of every size occur.
        robots = [Pusher(server.address, engine, k, period=p).start() for k, p in enumerate((0.05, 0.07, 0.11, 0.17))]
        time.sleep(seconds)
    finally:
        for r in robots:
            r.stop()
        server.stop(grace_s=0.5)
    return server


@pytest.mark.slow
def test_server_learns_the_measured_latency_from_a_wrong_profile(engine, caplog):
    wrong = LatencyProfile("wrong", (200.0, 300.0, 400.0))
    with caplog.at_level("WARNING", logger="lerobot_armory.serving.loop"):
        server = serve_for(engine, wrong, learn=True)
    assert server.loop.error is None
    table = server.scheduler.d_infer
    validate_latencies(table, "learnt")
    measured = {b: statistics.median(v) / 1000 for b, v in server.loop.stats.infer_ms.items() if len(v) >= 5}
    assert measured, f"no batch size served 5 times: {dict(server.loop.stats.batch_sizes)}"
    for b, seconds in measured.items():
        # Near what the batches really took (sleep 20 + 5b ms, plus this machine's overshoot).
        assert table[b - 1] == pytest.approx(seconds, rel=0.25), (b, table, measured)
    assert max(table) < 0.15  # every size left the wrong 200-400 ms, measured or fitted
    assert server.latency.max_drift().pct < -50
    assert "d_infer_drift=" in server.status_line()
    assert any("d_infer drifted" in r.getMessage() for r in caplog.records)
    exposition = generate_latest(server.metrics.registry).decode()
    assert 'armory_latency_estimate_seconds{batch_size="1"}' in exposition
    assert "armory_latency_drift_ratio" in exposition


def test_a_pinned_profile_does_not_move(engine):
    pinned = LatencyProfile("pinned", (200.0, 300.0, 400.0))
    server = serve_for(engine, pinned, learn=False, seconds=1.5)
    assert server.loop.error is None
    assert server.loop.stats.batches > 10
    assert server.scheduler.d_infer == pinned.table_s(3)
    assert server.latency.observed == 0 and server.latency.max_drift().pct == 0.0
    assert "d_infer=fixed" in server.status_line()


def test_a_lowered_cap_keeps_what_was_learnt_below_it_and_refuses_sizes_above():
    model = OnlineLatency(LatencyProfile("p", (10.0, 20.0, 30.0, 40.0)), 4, min_samples=3, confirm=3, window=5)
    for _ in range(3):
        model.observe(2, 0.050)  # b = 2 measured at 50 ms: the table moves
    before = model.table_s()
    model.lower_cap(2)
    assert model.max_batch_size == 2 and model.table_s() == before[:2] and model.table_s()[1] == pytest.approx(0.050)
    with pytest.raises(ValueError, match="outside 1..2"):
        model.observe(3, 0.030)
    model.lower_cap(3)  # raising is not lowering: nothing changes
    assert model.max_batch_size == 2
    model.observe(1, 0.030)
    assert len(model.table_s()) == 2
