"""A robot's clock offset and one-way delays, estimated from timestamp exchanges without
synchronised clocks, and the bounds on what robot-supplied times may claim. Pure: no I/O, no
clock reads (every time is passed in)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field


# Slack on offsets and times for float rounding and scheduling noise (seconds).
OFFSET_TOLERANCE_S = 0.005

# What robot-supplied times may claim (docs/spec.md §2, edge checks). A robot's one-way uplink is never
# believed above MAX_UPLINK_S: an observation "captured" earlier than that before it reached the
# server is treated as a clock fault, not as an old observation, so a lying clock can move its
# robot's predicted deadline by at most that much (less once server-measured round trips exist).
MAX_UPLINK_S = 0.5
MIN_UPLINK_WINDOW_S = 0.02
# Exchanges whose round trip is negative (beyond rounding) or longer than this are inconsistent.
MAX_ROUND_TRIP_S = 2.0
# Honest network jitter reorders observations by less than this; a capture time older than the
# latest by more is a clock fault (a step back), not a reordering.
REORDER_WINDOW_S = 1.0
# Consecutive implausible times before the robot's clock is declared stepped and re-synchronised.
CLOCK_FAULTS_FOR_STEP = 3



@dataclass
class DelayEstimator:
    """Estimates a robot's clock offset and one-way delays from timestamp exchanges.

    Each exchange is NTP-style: the robot stamps a message (``t_robot_send``, robot clock), the
    server stamps receipt and reply (``t_server_recv``, ``t_server_send``), the robot stamps the
    reply's arrival (``t_robot_recv``). Then ``offset = server - robot`` clock difference and the
    round trip are ``((r - a) + (s - b)) / 2`` and ``(b - a) - (s - r)``. The split of the round
    trip into uplink and downlink is not observable; we take half each. The error of that split
    cancels in what the mirror needs (when a chunk sent at server time ``s`` reaches the robot,
    expressed on the robot's own tick grid), so the mirror stays exact on average even when the
    network is asymmetric.

    Observations and execution reports give one exchange per served chunk; registration gives
    the first one. Running averages (EWMA with weight ``alpha``) smooth jitter.

    Robustness (the robot stamps two of the four times, and may lie or have its clock stepped):
    an exchange with a non-finite time or an impossible round trip is refused; an exchange whose
    offset disagrees with the estimate by more than both round trips allow is an outlier and is
    not folded in (an honest exchange's offset is off the true one by at most half its round
    trip, so honest jitter is never refused); ``CLOCK_FAULTS_FOR_STEP`` outliers in a row that
    agree with one another are a clock step: the estimate restarts from them. ``server_round_trip``
    folds in round trips the server timed on its own clock (its sync requests), which bound what
    the robot's stamps may claim.
    """

    alpha: float = 0.1
    offset_s: float = 0.0
    round_trip_s: float = 0.0
    samples: int = 0
    outliers: int = 0  # exchanges refused as outliers or inconsistent, in total
    steps: int = 0  # clock steps detected
    _pending: list[float] = field(default_factory=list)  # offsets of the current run of outliers
    _server_rtts: list[float] = field(default_factory=list)  # recent server-timed round trips

    def add_exchange(self, t_robot_send: float, t_server_recv: float, t_server_send: float, t_robot_recv: float) -> str:
        """Fold in one timestamp exchange (see class docstring).

        Returns ``"ok"`` (folded in), ``"refused"`` (non-finite or impossible round trip),
        ``"outlier"`` (disagrees with the estimate; not folded in) or ``"step"`` (a run of
        agreeing outliers: the estimate restarted from them).
        """
        offset = ((t_server_recv - t_robot_send) + (t_server_send - t_robot_recv)) / 2.0
        rtt = (t_robot_recv - t_robot_send) - (t_server_send - t_server_recv)
        if not (math.isfinite(offset) and math.isfinite(rtt)) or abs(rtt) > MAX_ROUND_TRIP_S:
            self.outliers += 1
            return "refused"
        rtt = min(max(0.0, rtt), self.round_trip_bound())
        if self.samples == 0:
            self.offset_s, self.round_trip_s = offset, rtt
            self.samples = 1
            return "ok"
        if abs(offset - self.offset_s) > (rtt + self.round_trip_s) / 2.0 + OFFSET_TOLERANCE_S:
            self.outliers += 1
            pending = self._pending
            if pending and abs(offset - pending[-1]) > rtt + OFFSET_TOLERANCE_S:
                pending.clear()  # the outliers do not agree with each other: noise, not a step
            pending.append(offset)
            if len(pending) < CLOCK_FAULTS_FOR_STEP:
                return "outlier"
            self.steps += 1
            self.offset_s = sorted(pending)[len(pending) // 2]
            self.round_trip_s = rtt
            pending.clear()
            return "step"
        self._pending.clear()
        self.offset_s += self.alpha * (offset - self.offset_s)
        self.round_trip_s += self.alpha * (rtt - self.round_trip_s)
        self.samples += 1
        return "ok"

    def server_round_trip(self, rtt: float) -> None:
        """A round trip the server timed itself (request sent → answer received, server clock):
        an upper bound of the true one that no robot stamp can inflate without answering late."""
        if math.isfinite(rtt) and rtt >= 0.0:
            self._server_rtts.append(min(rtt, MAX_ROUND_TRIP_S))
            del self._server_rtts[:-8]
            self.round_trip_s = min(self.round_trip_s, self.round_trip_bound())

    def round_trip_bound(self) -> float:
        """The longest round trip the robot's stamps may claim: the longest recent server-timed
        one, or ``2 * MAX_UPLINK_S`` before any."""
        return max(self._server_rtts) if self._server_rtts else 2.0 * MAX_UPLINK_S

    def uplink_window_s(self) -> float:
        """How long before its receipt an observation may plausibly have been captured."""
        return min(MAX_UPLINK_S, max(MIN_UPLINK_WINDOW_S, self.round_trip_bound()))

    def seed_offset(self, t_robot: float, t_server: float) -> None:
        """Before any exchange, take the clock offset from one one-way message assuming zero
        delay; the first real exchange replaces it (it is not counted as a sample)."""
        if self.samples == 0 and math.isfinite(t_server - t_robot):
            self.offset_s = t_server - t_robot

    def restart(self, t_robot: float, t_server: float) -> None:
        """The robot's clock stepped: forget the offset and seed it again from one message
        (robot-clock ``t_robot`` received at ``t_server``, less the known one-way delay); the
        next exchanges refine it. Delay estimates are kept (a clock step does not move packets)."""
        self.samples = 0
        self._pending.clear()
        self.steps += 1
        self.seed_offset(t_robot, t_server - self.one_way_s)

    @property
    def one_way_s(self) -> float:
        """Estimated one-way delay (used for both ``d_obs`` and ``d_action``)."""
        return self.round_trip_s / 2.0

    def to_server_time(self, t_robot: float) -> float:
        """Convert a robot-clock time to the server clock."""
        return t_robot + self.offset_s
