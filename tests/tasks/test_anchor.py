"""The correctness anchor: a trained checkpoint keeps its task success when served.

The committed push ACT (examples/checkpoints/metaworld-push-act, 48/50 in LeRobot's own
select_action loop on held-out seeds) runs in LeRobot's loop and through the real server to one
MetaWorld robot at 30 Hz, on the same seeds. A regression anywhere on the serving path that a
random-weight test cannot see (normalisation, feature order, an action one tick off, a chunk
meeting the wrong episode) drops the served success rate: before episode boundaries existed the
same checkpoint succeeded 4 times in 20 served (old episodes' chunks ran in the new world).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("metaworld", reason="the metaworld extra (metaworld==3.0.0, mujoco==3.3.2) is not installed")

from lerobot_armory.bench.tasks import TasksConfig, run_local, run_openpi, run_served, wilson  # noqa: E402

CHECKPOINT = Path(__file__).resolve().parents[2] / "examples" / "checkpoints" / "metaworld-push-act"
EPISODES = 8
FLOOR = 6  # of 8: a policy at the local 96 % falls below with probability 0.3 %; the broken boundaries' 20 % reaches it with 0.1 %


@pytest.fixture(scope="module")
def local():
    cfg = TasksConfig(policy_path=str(CHECKPOINT), task="push", mode="local", episodes=EPISODES)
    cfg.validate()
    return run_local(cfg)


@pytest.mark.slow
@pytest.mark.subprocess
def test_the_committed_checkpoint_succeeds_served_as_in_lerobots_own_loop(tmp_path, local):
    cfg = TasksConfig(policy_path=str(CHECKPOINT), task="push", mode="both", episodes=EPISODES, max_minutes=4.0)
    cfg.validate()
    served = run_served(cfg, tmp_path)
    print(json.dumps({"local": local["successes"], "served": served["successes"], "starved_pct": served["starvation_pct"]}))
    assert local["episodes"] == EPISODES and local["successes"] >= FLOOR, local  # deterministic: the seeds decide
    assert served["episodes"] == EPISODES, served
    assert served["successes"] >= FLOOR, served["per_robot"]
    seeds = [r["seed"] for r in served["per_robot"][0]["episode_results"]]
    assert seeds == [r["seed"] for r in local["episode_results"]] == list(range(1000, 1000 + EPISODES))


@pytest.mark.slow
@pytest.mark.subprocess
def test_through_the_openpi_endpoint_each_episode_ends_as_in_lerobots_own_loop(local):
    # openpi's client is synchronous (the world waits for each infer, h_min actions per chunk), as
    # LeRobot's loop is: the same chunks executed at the same ticks give the same episodes, tick for
    # tick. One episode of slack: the server's CPU pass may round differently from the local one.
    cfg = TasksConfig(policy_path=str(CHECKPOINT), task="push", mode="openpi", episodes=EPISODES)
    cfg.validate()
    openpi = run_openpi(cfg)
    pairs = list(zip(local["episode_results"], openpi["episode_results"], strict=True))
    assert all(a["seed"] == b["seed"] for a, b in pairs)
    differ = [(a, b) for a, b in pairs if (a["success"], a["ticks"]) != (b["success"], b["ticks"])]
    assert len(differ) <= 1, differ
    assert openpi["successes"] >= FLOOR, openpi


def test_wilson_interval():
    lo, hi = wilson(48, 50)
    assert 0.86 < lo < 0.87 and 0.98 < hi < 0.995
    assert wilson(0, 0) == (0.0, 1.0)
    assert wilson(10, 10)[1] == 1.0
