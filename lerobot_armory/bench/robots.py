"""A group of simulated robots in one process (``python -m lerobot_armory.bench.robots SPEC.json``).

The live benchmarks start a few of these so that a 2-core machine is not drowned in processes;
each robot (``armory_sim``, or ``metaworld`` where the group's ``kind`` says so) runs the real
:class:`~lerobot_armory.robot.client.ArmoryClient` loop in its own thread, with the emulated
network of the spec, and writes its stats JSON.
"""

from __future__ import annotations

import json
import logging
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from lerobot_armory.network_delay import LogNormalDelay
from lerobot_armory.robot.armory_sim import ArmorySim, ArmorySimConfig
from lerobot_armory.robot.client import ArmoryClient, Backoff, RobotIdentity
from lerobot_armory.robot.features import FeatureMap
from lerobot_armory.robot.netem import NetworkEmulator


def run_robot(spec: dict[str, Any], group: dict[str, Any]) -> dict[str, Any]:
    if group.get("kind", "armory_sim") == "metaworld":
        from lerobot_armory.robot.metaworld import MetaWorldRobot, MetaWorldRobotConfig

        robot = MetaWorldRobot(MetaWorldRobotConfig(task=spec["task"], seed=spec["seed"], episodes=spec.get("episodes", 0)))
        task_text = robot.config.task
    else:
        robot = ArmorySim(ArmorySimConfig(scene=spec["scene"], image_size=group["image_size"], seed=spec["seed"]))
        task_text = spec["scene"]
    robot.connect()
    fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
    net = LogNormalDelay(group["net_median_ms"] / 1000.0, group["net_sigma"])
    network = (lambda: NetworkEmulator(net, net, seed=spec["seed"])) if group["net_median_ms"] > 0 else None
    episodes = isinstance(getattr(robot, "episode", None), int) and not group.get("no_episode_boundaries", False)
    client = ArmoryClient(
        group["address"],
        RobotIdentity(
            spec["robot_id"], spec["fps"], spec["h_min"], spec["h_max"], spec["weight"], spec["tier"], task_text,
            policy_name=spec.get("policy_name", ""),
        ),
        fmap.wire_features(),
        observe=lambda: fmap.to_wire(robot.get_observation()),
        act=lambda vector: robot.send_action(fmap.to_action(vector)),
        backoff=Backoff(0.2, 1.0, give_up_s=30.0),
        network=network,
        episode_of=(lambda: robot.episode) if episodes else None,
        finished=(lambda: robot.finished) if hasattr(robot, "finished") else None,
    )
    try:
        stats = client.run(group["duration_s"])
    finally:
        client.close()
        robot.disconnect()
    stats.update(robot.task_stats())
    minutes = stats["ticks"] / spec["fps"] / 60.0
    stats["successes_per_min"] = stats["successes"] / minutes if minutes else 0.0
    stats.update({k: spec[k] for k in ("scene", "task", "fps", "h_min", "h_max", "weight") if k in spec})
    return stats


def run_all(robots: list[dict[str, Any]], run: Callable[[dict[str, Any]], dict[str, Any]], out: Path) -> None:
    """Run each robot spec on its own thread, write ``out/<robot_id>.json``; exit 1 naming every
    robot that failed (the bench then fails loudly)."""
    errors: list[str] = []

    def worker(spec: dict[str, Any]) -> None:
        try:
            stats = run(spec)
            (out / f"{spec['robot_id']}.json").write_text(json.dumps(stats, indent=2) + "\n")
        except Exception as exc:  # noqa: BLE001 - reported by the bench
            errors.append(f"{spec['robot_id']}: {type(exc).__name__}: {exc}")

    threads = [threading.Thread(target=worker, args=(spec,)) for spec in robots]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        print("\n".join(errors), file=sys.stderr)
        sys.exit(1)


def main(path: str) -> None:
    group = json.loads(Path(path).read_text())
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    run_all(group["robots"], lambda spec: run_robot(spec, group), Path(group["stats_dir"]))


if __name__ == "__main__":
    main(sys.argv[1])
