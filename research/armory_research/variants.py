"""Scheduler variants the study compares that are not product settings.

The product's Rollout (``lerobot_armory.schedulers.rollout``) picks its base policy per decision
from the load. The frontier study also reports Rollout whose rollouts always keep dispatching
batches of the candidate's size (``same``): the setting that reached >= 95 % of the best
schedule found on every small fleet when told the episode's end. Importing this module
registers it as ``--scheduler.type=rollout_same`` for the study's runs (never in the product).
"""

from __future__ import annotations

from dataclasses import dataclass

from lerobot_armory.latency import LatencyProfile
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
