"""The Rollout scheduler on its own: it is registered and validated, deterministic and within
the batch contract in the simulator (its queue arithmetic is the mirror's, tested in
``tests/core/test_mirror.py``).

Its comparison with the exact optimum on deterministic episodes is part of the offline study:
``research/tests/test_frontier.py`` (``make research``).
"""

from __future__ import annotations

import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import load_profile
from lerobot_armory.schedulers import make_scheduler_config, scheduler_names
from lerobot_armory.schedulers.rollout import RolloutConfig, RolloutScheduler
from lerobot_armory.sim import FleetSimulator, LogNormalDelay, fleet_specs, get_preset

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
