"""The scheduler interface and its registry (docs/spec.md §3).

A scheduler is a plain object that *decides*: given every robot's mirror and the time, it
returns the robots whose latest observations form the next batch. It does no I/O and keeps no
clock of its own, so the live server (wall time) and the simulator (simulated time) run the very
same objects.

Adding a scheduler is one file: a config dataclass registered under a name plus a
:class:`Scheduler` subclass that the config builds::

    @SchedulerConfig.register_subclass("mine")
    @dataclass
    class MineConfig(SchedulerConfig):
        knob: int = 3
        def build(self, profile, max_batch_size):
            return MineScheduler(profile, max_batch_size, self.knob)

then import the module from ``lerobot_armory/schedulers/__init__.py``, or, from another package,
declare it under the entry-point group ``lerobot_armory.schedulers`` (:mod:`.plugins`);
``--scheduler.type=mine`` selects it on every command line.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import draccus

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.schedulers.plugins import discover_once
from lerobot_armory.schedulers.dispatch_timing import check_timing, hold_until


@dataclass(frozen=True)
class DevicePeer:
    """Another policy sharing the device, as the arbiter shows it to a scheduler deciding now.

    Attributes:
        robots: that policy's robots' mirrors (registration order).
        d_infer: its batch latencies in seconds, index ``b - 1`` (its scheduler's ``d_infer``).
        max_batch_size: its batch cap.
    """

    robots: Sequence[RobotMirror]
    d_infer: Sequence[float]
    max_batch_size: int


class Scheduler(abc.ABC):
    """Chooses which robots share the next batch.

    Contract (checked by :func:`check_batch`): called only when the device is free and at least
    one robot :meth:`~RobotMirror.is_useful`; returns a non-empty list of distinct useful
    robots, at most ``max_batch_size`` long.

    Dispatch timing (:mod:`.timing`): with ``max_wait_s > 0`` the dispatcher asks :meth:`hold`
    after :meth:`select` whether to wait (at most ``max_wait_s`` per free device) for an
    observation about to land; with 0 (the default) the scheduler is work-conserving.
    """

    max_wait_s: float = 0.0
    wait_margin_s: float = 0.002
    # How an arbiter between policies sharing one device picks whose batch runs next
    # (lerobot_armory/arbiter.py): "deadline" (the soonest deadline), "rotate" (in turn) or
    # "score" (the highest ``last_score``, which the scheduler sets in ``select``).
    arbitration: str = "deadline"
    last_score: float | None = None
    # The other policies on the same device (lerobot_armory/arbiter.py): set by the arbiter for
    # one decision (select, then hold) when several policies share the device, () otherwise. A
    # scheduler that plans later batches (Rollout) must count their batches: the device is not
    # its own. The others may ignore it.
    peers: tuple[DevicePeer, ...] = ()

    def __init__(self, profile: LatencyProfile, max_batch_size: int) -> None:
        if max_batch_size < 1:
            raise ConfigError("max_batch_size", f"must be >= 1, got {max_batch_size}")
        self.profile = profile
        self.max_batch_size = max_batch_size
        # d_infer(b) in seconds, index b-1: looked up on every decision.
        self.d_infer = profile.table_s(max_batch_size)

    @abc.abstractmethod
    def select(self, robots: Sequence[RobotMirror], now: float) -> list[RobotMirror]:
        """Pick the next batch among ``robots`` (all robots, in registration order) at ``now``."""

    def hold(self, robots: Sequence[RobotMirror], batch: Sequence[RobotMirror], now: float) -> float | None:
        """The instant to wait for before dispatching ``batch`` (chosen at ``now``), or None to
        dispatch now. The default is :func:`.timing.hold_until` with this scheduler's knobs."""
        if self.max_wait_s <= 0:
            return None
        return hold_until(robots, batch, now, self.d_infer, self.max_wait_s, self.wait_margin_s)


def useful(robots: Sequence[RobotMirror]) -> list[RobotMirror]:
    """The robots whose latest observation is worth serving now (docs/spec.md §3)."""
    return [r for r in robots if r.is_useful()]


def check_batch(batch: Sequence[RobotMirror], max_batch_size: int, name: str) -> None:
    """Raise if a scheduler broke its contract (a bug in a plugin scheduler, never user input)."""
    if not batch:
        raise RuntimeError(f"scheduler {name!r} returned an empty batch although a useful request exists")
    if len(batch) > max_batch_size:
        raise RuntimeError(f"scheduler {name!r} returned {len(batch)} robots, above the cap {max_batch_size}")
    if len({id(r) for r in batch}) != len(batch):
        raise RuntimeError(f"scheduler {name!r} returned the same robot twice")
    for r in batch:
        if not r.is_useful():
            raise RuntimeError(f"scheduler {name!r} chose robot {r.spec.robot_id!r}, whose request is not useful")


@dataclass
class SchedulerConfig(draccus.ChoiceRegistry, abc.ABC):
    """Base of the per-scheduler configs; ``--scheduler.type=NAME`` picks a registered one.

    Attributes (every scheduler's, :mod:`.timing`):
        wait_ms: dispatch timing: the device may wait up to this long after it is free for an
            observation about to land, when the mirrors predict that its chunk lands as early and
            fresher and nobody else's chunk lands later (0: work-conserving, dispatch at once).
        wait_margin_ms: a wait must still pay off if the dispatch happens this much later
            (latency and network prediction error).
    """

    wait_ms: float = 0.0
    wait_margin_ms: float = 2.0

    @classmethod
    def default_choice_name(cls) -> str | None:
        """Lookahead is the default, so ``--scheduler.depth=2`` alone configures it."""
        return "lookahead"

    # draccus reads the registry through these two when it parses --scheduler.type: other
    # packages' schedulers (entry-point group lerobot_armory.schedulers) are loaded on first use.
    @classmethod
    def get_known_choices(cls) -> dict[str, Any]:
        discover_once()
        return super().get_known_choices()

    @classmethod
    def get_choice_class(cls, name: str) -> Any:
        discover_once()
        return super().get_choice_class(name)

    @property
    def type(self) -> str:
        """The registered name of this scheduler."""
        return self.get_choice_name(self.__class__)

    @abc.abstractmethod
    def build(self, profile: LatencyProfile, max_batch_size: int) -> Scheduler:
        """Instantiate the scheduler for a latency profile and batch cap (its own knobs only:
        drivers call :meth:`make`, which adds the dispatch timing)."""

    def make(self, profile: LatencyProfile, max_batch_size: int) -> Scheduler:
        """The scheduler, with this config's dispatch timing (``wait_ms``, ``wait_margin_ms``)."""
        for name, value in (("wait_ms", self.wait_ms), ("wait_margin_ms", self.wait_margin_ms)):
            try:
                check_timing(float(value) / 1000.0)
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"scheduler.{name}", str(exc)) from None
        scheduler = self.build(profile, max_batch_size)
        if self.wait_ms > 0:  # 0 leaves the scheduler's own timing (work-conserving by default)
            scheduler.max_wait_s = self.wait_ms / 1000.0
            scheduler.wait_margin_s = self.wait_margin_ms / 1000.0
        return scheduler

    def label(self) -> str:
        """Short name for tables and plots."""
        return self.type + self.timing_label()

    def timing_label(self) -> str:
        """`` +wait N ms`` when dispatch timing is on (appended to every label)."""
        return f" +wait {self.wait_ms:g} ms" if self.wait_ms > 0 else ""


def scheduler_names() -> list[str]:
    """Registered scheduler names."""
    return sorted(SchedulerConfig.get_known_choices())


def make_scheduler_config(name: str, **kwargs: object) -> SchedulerConfig:
    """Config of the scheduler registered as ``name`` (ConfigError if unknown)."""
    known = SchedulerConfig.get_known_choices()
    if name not in known:
        raise ConfigError("scheduler.type", f"unknown scheduler {name!r}; known: {', '.join(sorted(known))}")
    return known[name](**kwargs)
