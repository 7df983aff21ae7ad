"""Scheduler variants the study compares that are not product settings.

The product's Rollout (``lerobot_armory.schedulers.rollout``) picks its base policy per decision
from the load. The frontier study also reports Rollout whose rollouts always keep dispatching
batches of the candidate's size (``same``): the setting that reached >= 95 % of the best
schedule found on every small fleet when told the episode's end. Importing this module
registers it as ``--scheduler.type=rollout_same`` for the study's runs (never in the product),
and aligned EDF (``edf_aligned``: EDF that dispatches only at observation arrivals), the simple
non-work-conserving baseline of the true optimum's study.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.schedulers.edf import EarliestDeadlineScheduler
from lerobot_armory.schedulers.base import Scheduler, SchedulerConfig
from lerobot_armory.schedulers.rollout import RolloutConfig, RolloutScheduler


class SameTailRollout(RolloutScheduler):
    """Rollout whose later batches always have the candidate's size (the ``same`` base policy)."""

    def _tail(self, ranked, now, b) -> str:  # noqa: ANN001 - the product's private hook
        return "same"


@SchedulerConfig.register_subclass("rollout_same")
@dataclass
class SameTailRolloutConfig(RolloutConfig):
    """Rollout with the ``same`` base policy in every decision (study only)."""

    def build(self, profile: LatencyProfile, max_batch_size: int) -> Scheduler:
        return SameTailRollout(profile, max_batch_size, self.window_s)


class AlignedEdf(EarliestDeadlineScheduler):
    """EDF that dispatches only at observation arrivals ("aligned EDF", a study baseline).

    When the device is free between two arrivals it waits for the next one, then serves EDF's
    batch. The simplest rule that is not work-conserving: it re-aligns every batch with a fresh
    observation, which wins where a batch's latency just fits a number of ticks (libero) and
    loses where the wait only costs device time (piper). The product's dispatch timing
    (``--scheduler.wait_ms``) waits only when the mirrors predict it pays.
    """

    def __init__(self, profile: LatencyProfile, max_batch_size: int) -> None:
        super().__init__(profile, max_batch_size)
        self.max_wait_s = 1.0  # the driver wakes at the next arrival long before

    def hold(self, robots: Sequence[RobotMirror], batch: Sequence[RobotMirror], now: float) -> float | None:
        if any(m.obs_index is not None and abs(m.obs_recv - now) <= 1e-9 for m in robots):
            return None  # an observation landed just now: dispatch
        return now + self.max_wait_s


@SchedulerConfig.register_subclass("edf_aligned")
@dataclass
class AlignedEdfConfig(SchedulerConfig):
    """Aligned EDF (study only)."""

    def build(self, profile: LatencyProfile, max_batch_size: int) -> Scheduler:
        return AlignedEdf(profile, max_batch_size)
