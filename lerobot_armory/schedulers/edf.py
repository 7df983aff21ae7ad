"""Earliest Deadline First (docs/spec.md §3): serve the ``b`` useful robots that run dry soonest."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.schedulers.base import Scheduler, SchedulerConfig, useful


class EarliestDeadlineScheduler(Scheduler):
    """Deadline = time of the last control step covered by any chunk in ``Q_j``
    (:meth:`RobotMirror.deadline`); ties keep registration order."""

    def select(self, robots: Sequence[RobotMirror], now: float) -> list[RobotMirror]:
        ranked = sorted(enumerate(useful(robots)), key=lambda p: (p[1].deadline(), p[0]))
        return [r for _, r in ranked[: self.max_batch_size]]


@SchedulerConfig.register_subclass("edf")
@dataclass
class EarliestDeadlineConfig(SchedulerConfig):
    """EDF has no knobs."""

    def build(self, profile: LatencyProfile, max_batch_size: int) -> Scheduler:
        return EarliestDeadlineScheduler(profile, max_batch_size)
