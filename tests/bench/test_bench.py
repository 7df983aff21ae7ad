"""Latency emulation, network emulation, the analytic planner policy, and a short live bench."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from lerobot_armory.network_delay import LogNormalDelay
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.robot.armory_sim import ArmorySimEnv, WorldParams
from lerobot_armory.robot.netem import DelayLine, NetworkEmulator
from lerobot_armory.engine.emulation import EmulatedLatencyEngine
from lerobot_armory.engine.protocol import UnguidedEngine


class FakeEngine(UnguidedEngine):
    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def infer(self, observations, tasks, noise_seeds=None, history=None):
        time.sleep(self.seconds)
        return np.zeros((len(observations), 4, 2), np.float32)


def test_emulated_engine_takes_the_profiles_time_per_batch_size():
    profile = LatencyProfile("p", (40.0, 80.0, 120.0))
    engine = EmulatedLatencyEngine(FakeEngine(0.005), profile)
    for b, expect in ((1, 0.040), (3, 0.120)):
        start = time.perf_counter()
        out = engine.infer([{}] * b, [""] * b)
        took = time.perf_counter() - start
        assert out.shape[0] == b
        assert expect <= took < expect + 0.03
    assert engine.overruns == 0 and "emulated latency" in engine.label
    slow = EmulatedLatencyEngine(FakeEngine(0.05), LatencyProfile("p", (10.0,)))
    slow.infer([{}], [""])
    assert slow.overruns == 1 and slow.worst_overrun_ms > 30


def test_delay_line_runs_callbacks_in_due_order():
    line = DelayLine()
    seen = []
    done = threading.Event()
    now = time.monotonic()
    line.call_at(now + 0.06, lambda: (seen.append("late"), done.set()))
    line.call_at(now + 0.02, lambda: seen.append("early"))
    assert done.wait(2)
    assert seen == ["early", "late"]
    line.close()


def test_network_emulator_delays_exactly_with_zero_jitter():
    net = NetworkEmulator(LogNormalDelay(0.05, 0.0), LogNormalDelay(0.02, 0.0))
    got = {}
    done = threading.Event()
    start = time.monotonic()
    net.send(lambda: got.setdefault("up", time.monotonic() - start))
    net.receive(lambda: (got.setdefault("down", time.monotonic() - start), done.set()))
    time.sleep(0.12)
    assert 0.045 <= got["up"] < 0.09 and 0.015 <= got["down"] < 0.06
    net.close()


@pytest.fixture(scope="module")
def planner(tmp_path_factory):
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy
    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.engine.options import PolicyOptions

    path = tmp_path_factory.mktemp("planner") / "p"
    make_demo_policy(DemoPolicyConfig(output=str(path), kind="planner", chunk_size=10, image_size=64))
    return PolicyEngine(PolicyOptions(str(path), "cpu"))


def test_planner_loads_through_the_policy_path_and_aims_at_the_target(planner):
    assert planner.config.type == "armory_planner" and planner.chunk_size == 10
    env = ArmorySimEnv(WorldParams("static"), seed=3)
    env.reset()
    obs = env.observation()
    chunk = planner.infer([{"observation.state": obs["state"], "observation.images.front": obs["image"]}], [""])[0]
    assert chunk.shape == (10, 2)
    start = np.linalg.norm(env.target - env.effector)
    end = np.linalg.norm(env.target - chunk[-1])
    assert end < start - 0.3, "the chunk does not move toward the target"


def success_rate(planner, scene: str, replan_every: int, seconds: float = 20.0) -> int:
    env = ArmorySimEnv(WorldParams(scene), seed=1)
    env.reset()
    chunk, start = None, 0
    for k in range(int(30 * seconds)):
        if chunk is None or k - start >= replan_every:
            o = env.observation()
            chunk = planner.infer([{"observation.state": o["state"], "observation.images.front": o["image"]}], [""])[0]
            start = k
        env.set_goal(chunk[min(k - start, len(chunk) - 1)])
        env.advance(1 / 30)
    return env.successes


def test_planner_solves_both_tasks_fresh_and_dynamic_success_falls_when_stale(planner):
    fresh_static = success_rate(planner, "static", 2)
    fresh_dynamic = success_rate(planner, "dynamic", 2)
    stale_dynamic = success_rate(planner, "dynamic", 10)
    assert fresh_static >= 25 and fresh_dynamic >= 20  # about 1.5 targets per second
    assert stale_dynamic < 0.8 * fresh_dynamic


@pytest.mark.slow
@pytest.mark.subprocess
def test_short_live_bench_matches_the_simulator(tmp_path):
    from lerobot_armory.bench.live import BenchConfig, run

    runs = run(
        BenchConfig(robots=2, mix="one-fast", schedulers="edf", duration_s=6.0, groups=1, work_dir=str(tmp_path), output=str(tmp_path / "r.json"))
    )
    r = runs[0]
    assert r["live"] and "emulated latency" in r["latency_profile"]
    assert set(r["tiers"]) == {"fast", "slow"}
    for tier in ("fast", "slow"):
        assert r["tiers"][tier]["starvation_pct"] < 30
        assert abs(r["tiers"][tier]["starvation_pct"] - r["sim"][tier]) < 10
        # Every robot switches chunks many times in 6 s: the seam is measured (a finite jump).
        assert r["tiers"][tier]["seam_jump_mean"] >= 0.0 and r["tiers"][tier]["seam_jump_p95"] >= 0.0
        assert all(s["seams"] > 5 for s in r["per_robot"] if s["tier"] == tier)
    assert sum(r["batch_sizes"].values()) > 20 and 0 < r["cpu_busy_pct"] < 100
    assert (tmp_path / "r.json").is_file()
