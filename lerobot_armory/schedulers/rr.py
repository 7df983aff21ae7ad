"""Round Robin (docs/spec.md §3): a pointer cycles over the robots; each batch takes the next ``b``."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.schedulers.base import Scheduler, SchedulerConfig


class RoundRobinScheduler(Scheduler):
    """Walks the ring of robots from the pointer, taking useful robots until ``b`` are taken;
    the pointer then moves past the last robot taken. Robots are identified by id so robots
    joining or leaving do not reset the rotation."""

    arbitration = "rotate"  # several policies take turns, as robots do

    def __init__(self, profile: LatencyProfile, max_batch_size: int) -> None:
        super().__init__(profile, max_batch_size)
        self._last_id: str | None = None

    def select(self, robots: Sequence[RobotMirror], now: float) -> list[RobotMirror]:
        n = len(robots)
        start = 0
        if self._last_id is not None:
            ids = [r.spec.robot_id for r in robots]
            if self._last_id in ids:
                start = ids.index(self._last_id) + 1
        batch: list[RobotMirror] = []
        for k in range(n):
            robot = robots[(start + k) % n]
            if robot.is_useful():
                batch.append(robot)
                if len(batch) == self.max_batch_size:
                    break
        if batch:
            self._last_id = batch[-1].spec.robot_id
        return batch


@SchedulerConfig.register_subclass("rr")
@dataclass
class RoundRobinConfig(SchedulerConfig):
    """Round Robin has no knobs."""

    def build(self, profile: LatencyProfile, max_batch_size: int) -> Scheduler:
        return RoundRobinScheduler(profile, max_batch_size)
