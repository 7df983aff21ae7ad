"""The Rollout scheduler on its own: it is registered and validated, deterministic and within
the batch contract in the simulator (its queue arithmetic is the mirror's, tested in
``tests/core/test_mirror.py``).

Its comparison with the exact optimum on deterministic episodes is part of the offline study:
``research/tests/test_frontier.py`` (``make research``).
"""

from __future__ import annotations

import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile, load_profile
from lerobot_armory.schedulers import make_scheduler_config, scheduler_names
from lerobot_armory.schedulers.base import DevicePeer
from lerobot_armory.schedulers.rollout import RolloutConfig, RolloutScheduler
from lerobot_armory.sim import FleetSimulator, LogNormalDelay, fleet_specs, get_preset
from tests.support.mirrors import mirror, served

PROFILE = load_profile("l40s-pi05")


# ------------------------------------------------------------------------------------------
# Registered, validated, deterministic, within the batch contract


def test_rollout_is_registered_and_validates():
    assert "rollout" in scheduler_names()
    cfg = make_scheduler_config("rollout", window_s=0.8)
    assert isinstance(cfg, RolloutConfig) and cfg.type == "rollout"
    sched = cfg.build(PROFILE, 3)
    assert isinstance(sched, RolloutScheduler) and sched.window_s == 0.8
    with pytest.raises(ConfigError) as info:
        make_scheduler_config("rollout", window_s=0).build(PROFILE, 3)
    assert info.value.field == "scheduler.window_s"
    # The study's knobs were measured and left off the product (research/ keeps the study).
    for knob in ("tail", "order", "candidates", "keep_plan"):
        with pytest.raises(TypeError):
            make_scheduler_config("rollout", **{knob: 1})


@pytest.mark.parametrize(
    "preset, mix, n",
    [("libero", "one-fast", 10), ("piper", "half-fast", 6), ("libero", "all-fast", 3), ("piper", "one-fast", 10)],
)
def test_rollout_contract_and_determinism(preset, mix, n):
    specs = fleet_specs(get_preset(preset), mix, n, fast_weight=2.0)
    cap = get_preset(preset).default_batch_cap(mix)
    net = LogNormalDelay(0.00375, 0.3)
    runs = []
    for _ in range(2):
        sched = make_scheduler_config("rollout").build(PROFILE, cap)
        # FleetSimulator calls check_batch on every decision (non-empty, <= cap, distinct, useful).
        res = FleetSimulator(specs, sched, 8.0, net, net, seed=1).run()
        runs.append(([r.executed_steps for r in res.robots], dict(res.batch_sizes)))
        assert set(res.batch_sizes) <= set(range(1, cap + 1))
    assert runs[0] == runs[1]


# ------------------------------------------------------------------------------------------
# On a device shared with another policy (Scheduler.peers, set by the PolicyArbiter)

NOW = 1.0


def _holding(prefix: str, executed: list[int]) -> list:
    """Robots at 100 fps that each hold one chunk of 10 and have executed ``x`` of it by NOW."""
    out = []
    for k, x in enumerate(executed):
        m = mirror(robot_id=f"{prefix}{k}", fps=100.0, h_min=1, h_max=10)
        t0 = NOW - x / 100.0
        m.on_observation(0, t0, t0)
        served(m, t0)
        m.on_observation(x, NOW, NOW)
        out.append(m)
    return out


def test_rollout_serves_now_what_a_slow_peers_batch_would_starve():
    """A flat 10 ms policy whose robots run dry in 20, 50, 70 and 90 ms. Alone it serves the first
    just in time (the others later, fresher, at no cost: the device is its own). Beside a policy
    whose robot runs dry in 30 ms and whose batch takes 80-100 ms, that batch runs next and the
    others would starve behind it: it serves all four now, at the same 10 ms."""
    flat = LatencyProfile("flat", (10.0,) * 4)
    fast = _holding("f", [8, 5, 3, 1])
    assert [round(m.deadline() - NOW, 3) for m in fast] == [0.02, 0.05, 0.07, 0.09]
    alone = RolloutScheduler(flat, 4)
    assert [m.spec.robot_id for m in alone.select(fast, NOW)] == ["f0"]
    shared = RolloutScheduler(flat, 4)
    slow = _holding("s", [7, 1, 1])
    shared.peers = (DevicePeer(slow, LatencyProfile("slow", (80.0, 90.0, 100.0)).table_s(3), 3),)
    assert [m.spec.robot_id for m in shared.select(fast, NOW)] == ["f0", "f1", "f2", "f3"]
    # A peer with no robot is no peer: the decision is the one alone.
    shared.peers = (DevicePeer([], (0.08,), 1),)
    assert [m.spec.robot_id for m in shared.select(fast, NOW)] == ["f0"]
