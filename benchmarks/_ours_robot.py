"""One robot (``armory_sim``, or ``metaworld`` where the spec says so) on the armory client, instrumented for ``benchmarks/vs_lerobot_async.py``.

``python benchmarks/_ours_robot.py SPEC.json``: connects (registers) to the armory server, says
it is ready, waits for the benchmark's start signal, runs the real
:class:`~lerobot_armory.robot.client.ArmoryClient` loop for ``duration_s`` and writes a stats JSON
with the same keys as the stock side (``benchmarks/_stock_async.py``): ticks, starved ticks (also
counted from the first chunk on), chunks received and chunk latency (observation capture -> chunk
received, both on the robot's clock), and the robot's task results (episodes, successes) where it
has them.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _stock_async import wait_for_go

from lerobot_armory.robot.armory_sim import ArmorySim, ArmorySimConfig
from lerobot_armory.robot.client import ArmoryClient, Backoff, RobotIdentity
from lerobot_armory.robot.connection import ReceivedChunk
from lerobot_armory.robot.features import FeatureMap


class TimedClient(ArmoryClient):
    """The armory client; the overrides only count, then call the client's own method."""

    def __init__(self, *args: Any, settle_chunks: int = 1, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.settle_chunks = settle_chunks  # ticks count as "after first" once this many chunks came
        self.latencies_s: list[float] = []
        self.first_chunk_time: float | None = None
        self.ticks_after_first = 0
        self.starved_after_first = 0

    def _on_chunk(self, epoch: int, chunk: ReceivedChunk) -> None:
        before = self.chunks_received
        super()._on_chunk(epoch, chunk)
        if self.chunks_received > before:  # accepted (not a chunk of a dead session)
            self.latencies_s.append(chunk.arrival_time - chunk.obs_capture_time)
            if self.first_chunk_time is None:
                self.first_chunk_time = chunk.arrival_time

    def step(self) -> bool:
        had_chunk = self.chunks_received >= self.settle_chunks
        executed = super().step()
        if had_chunk:
            self.ticks_after_first += 1
            self.starved_after_first += not executed
        return executed


def make_robot(spec: dict[str, Any]) -> Any:
    """The spec's robot (not connected)."""
    if spec.get("robot_kind", "armory_sim") == "metaworld":
        from lerobot_armory.robot.metaworld import MetaWorldRobot, MetaWorldRobotConfig

        return MetaWorldRobot(MetaWorldRobotConfig(id=spec["robot_id"], task=spec["task"], seed=spec["seed"], episodes=spec.get("episodes", 0)))
    return ArmorySim(ArmorySimConfig(scene=spec["scene"], image_size=spec["image_size"], seed=spec["seed"]))


def run_robot(spec: dict[str, Any]) -> dict[str, Any]:
    """Connect, wait for the start signal, run ``duration_s``; returns the stats."""
    robot = make_robot(spec)
    fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
    client = TimedClient(
        spec["address"],
        RobotIdentity(spec["robot_id"], spec["fps"], spec["h_min"], spec["h_max"]),
        fmap.wire_features(),
        observe=lambda: fmap.to_wire(robot.get_observation()),
        act=lambda vector: robot.send_action(fmap.to_action(vector)),
        backoff=Backoff(0.2, 1.0, give_up_s=30.0),
        settle_chunks=int(spec.get("settle_chunks", 1)),
        episode_of=(lambda: robot.episode) if hasattr(robot, "task_stats") else None,
        finished=(lambda: robot.finished) if hasattr(robot, "finished") else None,
    )
    robot.connect()
    try:
        client.connect()
        wait_for_go(Path(spec["ready_path"]), Path(spec["go_path"]))
        start = client.clock()
        base = client.run(spec["duration_s"])
        wall = client.clock() - start
    finally:
        client.close()
        robot.disconnect()
    ticks, after = base["ticks"], client.ticks_after_first
    task = robot.task_stats() if hasattr(robot, "task_stats") else {}
    return {
        **task,
        "robot_id": spec["robot_id"],
        "wall_s": wall,
        "ticks": ticks,
        "starved_steps": base["starved_steps"],
        "executed_steps": base["executed_steps"],
        "starvation_pct_all": base["starvation_pct"] if ticks else 100.0,
        "settle_chunks": client.settle_chunks,
        "ticks_after_first": after,
        "starved_after_first": client.starved_after_first,
        "starvation_pct": 100.0 * client.starved_after_first / after if after else 100.0,
        "chunks_received": base["chunks_received"],
        "foreign_chunks": 0,
        "observations_sent": ticks,
        "first_chunk_s": (client.first_chunk_time - start) if client.first_chunk_time is not None else None,
        "latency_ms": [1000.0 * x for x in client.latencies_s],
        "reconnects": base["reconnects"],
    }


def main(path: str) -> None:
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    spec = json.loads(Path(path).read_text())
    stats = run_robot(spec)
    Path(spec["stats_path"]).write_text(json.dumps(stats) + "\n")


if __name__ == "__main__":
    main(sys.argv[1])
