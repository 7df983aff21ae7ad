"""Where in its control tick a robot observes, on a simulator whose world steps when an action is sent.

    python benchmarks/tasks/tick_order.py --episodes=100 --out=docs/results/tasks      # ~3 min on 2 cores

The side by side at the task level found LeRobot's async ``robot_client`` far behind ours on push
even when given our episode boundary, and a few points ahead on the dynamic task. The two clients
order a tick differently, which matters only when the world jumps at ``send_action`` (a simulator
stepped once per action):

- **observe, then act** (``lerobot-armory-client``): the observation stamped ``i`` is taken before
  the tick's action ``i``; with a chunk back within the tick, the robot executes action ``i`` of
  the chunk it holds, then the new chunk from its action 1 on. On a real arm, which moves during
  the tick rather than at ``send_action``, each new action starts exactly one tick after the
  observation, as the chunk plans.
- **act, then observe** (LeRobot's ``robot_client``): the observation is taken right after the
  tick's action ``t`` and stamped ``t``; the chunk's action 0 carries that stamp, counts as
  executed and is dropped, so the next tick executes action 1 on the very state observed.

Each order is replayed here in simulated time with the committed checkpoints, a chunk asked for
every ``h_min`` = 10 executed actions and answered within the tick, on seeds 1000 on, beside
LeRobot's synchronous loop (the world waits; action 0 on the observed state). Writes
``tick_order.json`` under ``--out`` and prints the table.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from lerobot_armory.bench.tasks import TasksConfig, chunk_of, episode_summary, load_local, observation_of, run_local
from lerobot_armory.robot.metaworld.tasks import MetaWorldTask
from _checkpoints import CHECKPOINTS  # benchmarks/tasks/: the script's own directory

H_MIN = 10


def act_then_observe(path: str, task_name: str, seeds: range) -> list[dict[str, Any]]:
    """LeRobot's async client's tick order with a chunk back within the tick: after every
    ``H_MIN`` executed actions, observe after the tick's action and continue from the new chunk's
    action 1 at the next tick (the first chunk of an episode, observed before any action, from 0)."""
    policy, pre, post, _ = load_local(path, H_MIN)
    task = MetaWorldTask(task_name)
    results = []
    for seed in seeds:
        task.reset(seed)
        actions, k, since = chunk_of(policy, pre, post, observation_of(task)), 0, 0
        while not task.step(actions[k]).done:
            k, since = k + 1, since + 1
            if since >= H_MIN:
                actions, k, since = chunk_of(policy, pre, post, observation_of(task)), 1, 0
        results.append({"seed": seed, "success": bool(task.success), "ticks": task.ticks})
    task.close()
    return results


def summary(results: list[dict[str, Any]]) -> dict[str, Any]:
    record = episode_summary("local", results, mean_ticks=sum(r["ticks"] for r in results) / len(results))
    del record["mode"]
    return {**record, "interval95": list(record["interval95"])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--tasks", default=",".join(CHECKPOINTS))
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    rows = []
    for name in args.tasks.split(","):
        cfg = TasksConfig(policy_path=str(CHECKPOINTS[name]), task=name, mode="local", episodes=args.episodes)
        cfg.validate()
        orders = {
            "LeRobot's synchronous loop": run_local(cfg)["episode_results"],
            "act, then observe (LeRobot's async client)": act_then_observe(cfg.policy_path, name, range(cfg.seed, cfg.seed + args.episodes)),
            "observe, then act (ours)": run_local(replace(cfg, latency_ticks=1))["episode_results"],
        }  # fmt: skip
        for order, results in orders.items():
            rows.append({"task": name, "order": order, **summary(results)})
            print(json.dumps({k: v for k, v in rows[-1].items() if k != "episode_results"}), flush=True)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "tick_order.json").write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows}, indent=2) + "\n")
    print("| task | tick order | successes | rate [95 %] | mean ticks per episode |")
    print("|---|---|---|---|---|")
    for r in rows:
        lo, hi = r["interval95"]
        print(f"| {r['task']} | {r['order']} | {r['successes']}/{r['episodes']} | {r['success_rate']:.2f} [{lo:.2f}, {hi:.2f}] | {r['mean_ticks']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
