"""One registered robot's session, its state grouped by concern.

- :class:`Link`: the connection (stream open or not, who registered it, what it was granted, its
  rate limits);
- :class:`ClockExchanges`: the clock-offset exchanges in flight (the mirror's estimator keeps
  their results);
- :class:`SessionCounters`: what the robot reported and what was counted for it (metrics,
  status);
- :class:`DeviceShare`: device time spent on it (the grant rules's ``max_device_share``);
- on the session itself: its spec, task, features, mirror, latest observation, outbox, the chunks
  RTC cuts the next leftovers from, and a pending move.

All of it is read and written under the fleet's lock (:class:`~lerobot_armory.serving.fleet.Fleet`).
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

import numpy as np

from lerobot_armory.arbiter import DEFAULT_POLICY
from lerobot_armory.feature_spec import FeatureSpec
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.serving.messages import Grant
from lerobot_armory.serving.outbox import Outbox
from lerobot_armory.serving.security import RateLimiter

# Execution reports: a robot sends ~5 a second; more are dropped before any work.
REPORT_RATE_HZ = 20.0


@dataclass
class Link:
    """The robot's connection: whether its stream is open, who registered it (a digest of the
    token; None without auth), what the grant rules granted, and its rate limits."""

    streaming: bool = False
    credential: bytes | None = None
    grant: Grant | None = None
    obs_rate: RateLimiter | None = None  # observations (None: no limit)
    notified_at: float = 0.0  # when a flood was last told about (one notice a second)
    report_rate: RateLimiter = field(default_factory=lambda: RateLimiter(REPORT_RATE_HZ))


@dataclass
class ClockExchanges:
    """Clock exchanges in flight: the registration round trip's server stamps (the robot
    completes it with a ClockSync), and the sync requests sent and not yet answered."""

    register_stamps: tuple[float, float] | None = None
    pending: dict[int, float] = field(default_factory=dict)  # sync_id -> server send time
    next_id: int = 1
    next_at: float = 0.0


@dataclass
class SessionCounters:
    """Reported by the robot, or counted here."""

    observations: int = 0
    rejected: int = 0
    chunks_sent: int = 0
    reported_executed: int = 0
    reported_starved: int = 0
    reported_index: int | None = None
    index_error: int | None = None  # |mirror's predicted index - robot's reported index| at last report
    last_chunk_time: float | None = None
    first_executed: collections.Counter = field(default_factory=collections.Counter)

    @property
    def reported_starvation_pct(self) -> float:
        total = self.reported_executed + self.reported_starved
        return 100.0 * self.reported_starved / total if total else 0.0


@dataclass
class DeviceShare:
    """Decayed device seconds spent on this robot, and when they were last decayed."""

    seconds: float = 0.0
    at: float = 0.0


@dataclass
class RobotSession:
    """A registered robot: its spec, mirror, latest observation and outbox, and its state by concern."""

    session_id: str
    spec: RobotSpec
    task: str
    features: dict[str, FeatureSpec]
    mirror: RobotMirror
    registered_at: float
    outbox: Outbox = field(default_factory=Outbox)
    latest: dict[str, np.ndarray] | None = None
    # With a policy that reads an observation history: the last observations by index (the
    # latest included), enough for one row (None: the policy needs the latest alone).
    recent: collections.deque[tuple[int, dict[str, np.ndarray]]] | None = None
    link: Link = field(default_factory=Link)
    clock: ClockExchanges = field(default_factory=ClockExchanges)
    counters: SessionCounters = field(default_factory=SessionCounters)
    share: DeviceShare = field(default_factory=DeviceShare)
    # With RTC: the chunks sent, in the policy's action space, by chunk id (the leftovers of the
    # next requests are cut from them); only chunks still in the mirror's queue are kept.
    model_chunks: dict[int, np.ndarray] = field(default_factory=dict)
    # A cluster's front asked to move this robot to another replica: done right after the chunk
    # in flight is queued, so the robot never loses a chunk it was promised.
    move_after_chunk: bool = False
    # The policy that serves this robot (the server's only one unless it serves several).
    policy: str = DEFAULT_POLICY

    @property
    def robot_id(self) -> str:
        return self.spec.robot_id

    def remember(self, index: int, arrays: dict[str, np.ndarray]) -> None:
        """Keep an observation for the history, one per index (a resent index replaces its own,
        so that repeats cannot push the earlier ticks out)."""
        assert self.recent is not None
        if self.recent and self.recent[-1][0] == index:
            self.recent[-1] = (index, arrays)
        else:
            self.recent.append((index, arrays))

    def history(self, steps: int) -> list[dict[str, np.ndarray]]:
        """The observations of the ``steps`` control ticks ending at the latest, oldest first.

        A tick the robot sent nothing for (dropped, or before its first) takes the observation
        held then, or the first one: LeRobot fills a fresh episode's history the same way.
        """
        if self.latest is None:
            raise ValueError(f"{self.robot_id}: no observation yet")
        held = list(self.recent) if self.recent else []
        if not held:
            return [self.latest] * steps
        last = held[-1][0]
        out = []
        for tick in range(last - steps + 1, last + 1):
            at = [obs for index, obs in held if index <= tick]
            out.append(at[-1] if at else held[0][1])
        return out
