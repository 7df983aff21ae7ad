"""Schedulers behind one registry: ``rr``, ``edf``, ``lookahead`` (docs/spec.md §3).

Importing this package registers the built-in schedulers with :class:`SchedulerConfig`; a new
scheduler is one module plus an import line here. Other installed packages add schedulers through
the entry-point group ``lerobot_armory.schedulers`` (:mod:`.plugins`), loaded the first time the
registry is read.
"""

from lerobot_armory.schedulers import edf, lookahead, rollout, rr  # noqa: F401  (registration side effect)
from lerobot_armory.schedulers.base import (
    Scheduler,
    SchedulerConfig,
    check_batch,
    make_scheduler_config,
    scheduler_names,
    useful,
)
from lerobot_armory.schedulers.edf import EarliestDeadlineConfig, EarliestDeadlineScheduler
from lerobot_armory.schedulers.lookahead import LookaheadConfig, LookaheadScheduler
from lerobot_armory.schedulers.plugins import ENTRY_POINT_GROUP, load_scheduler_plugins
from lerobot_armory.schedulers.rr import RoundRobinConfig, RoundRobinScheduler

__all__ = [
    "ENTRY_POINT_GROUP",
    "EarliestDeadlineConfig",
    "EarliestDeadlineScheduler",
    "LookaheadConfig",
    "LookaheadScheduler",
    "RoundRobinConfig",
    "RoundRobinScheduler",
    "Scheduler",
    "SchedulerConfig",
    "check_batch",
    "load_scheduler_plugins",
    "make_scheduler_config",
    "scheduler_names",
    "useful",
]
