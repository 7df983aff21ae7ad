"""The chunk mirror: robot specs, chunk queues, delay estimates and *the* transition (SPEC §2).

Everything here is pure and deterministic: no I/O, no threads, no clock reads. Time is always
passed in, so the live server drives these objects with wall time and the simulator drives the
very same objects with simulated time ("one mirror, two clocks").

Time model. A robot ticks at ``fps``. At every tick it first captures and sends its observation
(tagged with its current action index ``i``), then executes action ``i`` iff some *arrived* chunk
covers ``i`` (``i_start <= i < i_start + h``) and advances ``i <- i + 1``; otherwise it starves and
``i`` stays. Ticks are counted on an integer grid from an *anchor* (a time at which a tick
happens), so a chunk's arrival becomes the first tick at or after its arrival time. Working on
integer ticks keeps the transition exact (no float drift over a 5-minute run) and lets it skip
whole runs of ticks at once, which is what makes Lookahead fast enough to search online.

The single transition is :func:`advance`. The robot's ground truth in the simulator
(:class:`RobotTimeline`) and the server's prediction (:class:`RobotMirror`) both call it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from lerobot_armory.errors import ConfigError

# Tolerance when mapping a time onto the tick grid: a chunk that arrives exactly at a tick
# (t_arrival == tick time, up to float rounding) counts as arrived at that tick (SPEC: t_arrival
# <= tick time).
_EPS = 1e-9

TIERS = ("fast", "slow")


@dataclass(frozen=True)
class RobotSpec:
    """What a robot declares when it joins: its control rate, horizon and importance.

    Attributes:
        robot_id: unique name of the robot in the fleet.
        fps: control frequency f_c (robot steps per second).
        chunk_size: H, actions per predicted chunk.
        h_min: the server does not serve the robot again before it executed this many steps
            since the observation of its last served request.
        h_max: the robot executes at most this many actions of a chunk.
        weight: w_j, value of one executed second of this robot (Lookahead's objective).
        tier: reporting label, ``fast`` (dynamic task, short h_max) or ``slow``.
    """

    robot_id: str
    fps: float
    chunk_size: int
    h_min: int
    h_max: int
    weight: float = 1.0
    tier: str = "slow"

    def __post_init__(self) -> None:
        if not self.robot_id:
            raise ConfigError("robot_id", "must be a non-empty string")
        if not (isinstance(self.fps, (int, float)) and math.isfinite(self.fps) and self.fps > 0):
            raise ConfigError("fps", f"must be a positive number of steps per second, got {self.fps!r}")
        if self.chunk_size < 1:
            raise ConfigError("chunk_size", f"must be >= 1, got {self.chunk_size}")
        if self.h_min < 0:
            raise ConfigError("h_min", f"must be >= 0, got {self.h_min}")
        if self.h_max < 1:
            raise ConfigError("h_max", f"must be >= 1, got {self.h_max}")
        if self.h_min > self.h_max:
            raise ConfigError("h_min", f"h_min={self.h_min} is larger than h_max={self.h_max}")
        if self.h_max > self.chunk_size:
            raise ConfigError("h_max", f"h_max={self.h_max} is larger than the chunk size H={self.chunk_size}")
        if not (math.isfinite(self.weight) and self.weight > 0):
            raise ConfigError("weight", f"must be a positive number, got {self.weight!r}")
        if self.tier not in TIERS:
            raise ConfigError("tier", f"must be one of {', '.join(TIERS)}, got {self.tier!r}")


@dataclass(slots=True)
class Chunk:
    """A chunk generated for one robot: actions for indices ``[i_start, i_start + h)``.

    ``t_arrival`` is in the clock of the timeline that owns the chunk: the server's estimate of
    when the robot will hold it (mirror), or the true arrival time (simulated ground truth).
    A chunk still in inference or on the network is simply one whose arrival is in the future.
    """

    chunk_id: int
    i_start: int
    h: int
    t_arrival: float

    @property
    def end(self) -> int:
        """First index the chunk does *not* cover."""
        return self.i_start + self.h


# A chunk on a tick grid: (i_start, end, arrival_tick). Tuples keep the hot loop cheap.
TickChunk = tuple[int, int, int]


def tick_of(t: float, anchor: float, fps: float) -> int:
    """First tick (counted from the tick at ``anchor``) whose time is >= ``t``."""
    return math.ceil((t - anchor) * fps - _EPS)


def reach(index: int, chunks: Sequence[TickChunk], tick: int) -> int:
    """First index at or after ``index`` that no chunk arrived by ``tick`` covers.

    ``chunks`` must be sorted by ``i_start``; one pass then follows overlapping chunks.
    """
    r = index
    for start, end, arrival in chunks:
        if arrival <= tick and start <= r < end:
            r = end
    return r


def advance(
    index: int,
    chunks: Sequence[TickChunk],
    n_ticks: int,
    on_use: Callable[[int, int], None] | None = None,
) -> int:
    """THE transition: run ``n_ticks`` control ticks (ticks ``0 .. n_ticks-1``) of one robot.

    At each tick the robot executes index ``i`` and advances iff a chunk that has arrived
    (``arrival_tick <= tick``) covers ``i``; otherwise it starves. Between two chunk arrivals the
    set of usable chunks is fixed, so the robot runs straight to the end of the covered stretch
    and then starves until the next arrival: the loop is over arrivals, not over ticks.

    Args:
        index: action index before tick 0.
        chunks: ``(i_start, end, arrival_tick)`` sorted by ``i_start`` (ties: older first).
        n_ticks: ticks to run (<= 0 runs none).
        on_use: if given, called as ``on_use(position_in_chunks, first_index_offset)`` each time
            the robot switches to a chunk (naive async: at each tick the newest arrived chunk
            covering the index is the one executed). Within one call a chunk is reported once;
            a caller that splits a run over several calls dedupes by chunk (the simulator does).
            Used for the first-executed-index metric; the schedulers' rollouts leave it out.

    Returns:
        The index after the ticks; executed steps = result - ``index``, starved = n_ticks - that.
    """
    if n_ticks <= 0:
        return index
    i = index
    bounds = sorted({a for _, _, a in chunks if 0 < a < n_ticks})
    bounds.append(n_ticks)
    tick = 0
    reported: set[int] = set()
    for bound in bounds:
        run = bound - tick
        covered = reach(i, chunks, tick) - i
        if covered < run:
            run = covered
        if run > 0 and on_use is not None:
            _report_uses(i, i + run, chunks, tick, reported, on_use)
        i += run
        tick = bound
    return i


def _report_uses(
    lo: int, hi: int, chunks: Sequence[TickChunk], tick: int, reported: set[int], on_use: Callable[[int, int], None]
) -> None:
    """Tell ``on_use`` which chunk executes indices ``lo .. hi-1`` (newest covering chunk wins)."""
    x = lo
    while x < hi:
        for pos in range(len(chunks) - 1, -1, -1):
            start, end, arrival = chunks[pos]
            if arrival <= tick and start <= x < end:
                if pos not in reported:
                    reported.add(pos)
                    on_use(pos, x - start)
                x = end
                break
        else:  # pragma: no cover - advance() only asks for covered stretches
            raise AssertionError("uncovered index inside an executed run")


def ticks_until_dry(index: int, chunks: Sequence[TickChunk]) -> int:
    """Ticks from tick 0 until the robot starves with every known chunk arrived.

    This is when the robot runs dry if no new chunk is generated (EDF's deadline).
    """
    last = max((a for _, _, a in chunks), default=0)
    last = max(last, 0)
    i = advance(index, chunks, last)
    return last + reach(i, chunks, last) - i


# --------------------------------------------------------------------------------------------
# Delay estimation without synchronised clocks


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
    """

    alpha: float = 0.1
    offset_s: float = 0.0
    round_trip_s: float = 0.0
    samples: int = 0

    def add_exchange(self, t_robot_send: float, t_server_recv: float, t_server_send: float, t_robot_recv: float) -> None:
        """Fold in one timestamp exchange (see class docstring)."""
        offset = ((t_server_recv - t_robot_send) + (t_server_send - t_robot_recv)) / 2.0
        rtt = max(0.0, (t_robot_recv - t_robot_send) - (t_server_send - t_server_recv))
        if self.samples == 0:
            self.offset_s, self.round_trip_s = offset, rtt
        else:
            self.offset_s += self.alpha * (offset - self.offset_s)
            self.round_trip_s += self.alpha * (rtt - self.round_trip_s)
        self.samples += 1

    def seed_offset(self, t_robot: float, t_server: float) -> None:
        """Before any exchange, take the clock offset from one one-way message assuming zero
        delay; the first real exchange replaces it (it is not counted as a sample)."""
        if self.samples == 0:
            self.offset_s = t_server - t_robot

    @property
    def one_way_s(self) -> float:
        """Estimated one-way delay (used for both ``d_obs`` and ``d_action``)."""
        return self.round_trip_s / 2.0

    def to_server_time(self, t_robot: float) -> float:
        """Convert a robot-clock time to the server clock."""
        return t_robot + self.offset_s


# --------------------------------------------------------------------------------------------
# Timelines: one robot's index evolving over a tick grid


@dataclass
class RobotTimeline:
    """A robot's index advancing over its tick grid, from tick ``tick`` at ``anchor + tick/fps``.

    The simulator's ground-truth robot is a timeline with true chunk arrivals; the mirror builds
    a throw-away timeline from the latest observation with estimated arrivals. Both move only
    through :func:`advance`.
    """

    fps: float
    anchor: float
    index: int = 0
    tick: int = 0
    chunks: list[Chunk] = field(default_factory=list)

    def tick_time(self, tick: int) -> float:
        """Time at which tick ``tick`` happens."""
        return self.anchor + tick / self.fps

    def ticks_before(self, t: float) -> int:
        """Number of ticks (from tick 0) that happen strictly before ``t``."""
        return max(0, tick_of(t, self.anchor, self.fps))

    def tick_chunks(self, origin: int) -> list[TickChunk]:
        """The chunks on the grid with tick ``origin`` renumbered as 0."""
        return [(c.i_start, c.end, tick_of(c.t_arrival, self.anchor, self.fps) - origin) for c in self.chunks]

    def add_chunk(self, chunk: Chunk) -> None:
        """Add a chunk, keeping the list sorted by ``(i_start, chunk_id)``."""
        self.chunks.append(chunk)
        if len(self.chunks) > 1 and (self.chunks[-2].i_start, self.chunks[-2].chunk_id) > (chunk.i_start, chunk.chunk_id):
            self.chunks.sort(key=lambda c: (c.i_start, c.chunk_id))

    def run_to(self, tick: int, on_use: Callable[[Chunk, int], None] | None = None) -> int:
        """Advance to ``tick`` (ticks ``self.tick .. tick-1`` run). Returns executed steps."""
        n = tick - self.tick
        if n <= 0:
            return 0
        hook = None
        if on_use is not None:
            chunks = self.chunks

            def hook(pos: int, offset: int) -> None:
                on_use(chunks[pos], offset)

        before = self.index
        self.index = advance(self.index, self.tick_chunks(self.tick), n, hook)
        self.tick = tick
        self.prune()
        return self.index - before

    def prune(self) -> None:
        """Drop chunks that can never be executed again (they end at or before the index)."""
        if any(c.end <= self.index for c in self.chunks):
            self.chunks = [c for c in self.chunks if c.end > self.index]


# --------------------------------------------------------------------------------------------
# The server-side mirror of one robot


@dataclass
class WindowView:
    """One robot's mirror frozen at a decision time, on its tick grid (for schedulers).

    ``index`` is the predicted index before tick 0 (the first tick at or after the decision
    time), ``chunks`` the known chunks on that grid, ``window_ticks`` the ticks inside the reward
    window. ``arrival_tick(t)`` maps an absolute (server-clock) time onto that grid.
    """

    mirror: RobotMirror
    now: float
    index: int
    origin_time: float
    chunks: list[TickChunk]
    window_ticks: int

    def arrival_tick(self, t: float) -> int:
        """Tick (on this view's grid) of the first tick at or after ``t``."""
        return tick_of(t, self.origin_time, self.mirror.spec.fps)

    def executed(self, extra: Sequence[TickChunk] = ()) -> int:
        """Steps executed inside the window, with ``extra`` chunks added to the known ones."""
        chunks = self.chunks
        if extra:
            chunks = sorted([*chunks, *extra])
        return advance(self.index, chunks, self.window_ticks) - self.index


@dataclass
class RobotMirror:
    """The server's model of one robot (SPEC §2): ``i_j``, ``î_j``, ``Q_j`` and delay estimates.

    Fed by three events, each with the time it happened on the server clock:

    - :meth:`on_observation`: an observation with index ``î`` captured at a robot-clock time;
    - :meth:`on_dispatch`: a batch containing this robot finishes inference at ``t_done``;
    - :meth:`on_report`: the robot says when a chunk reached it (one delay exchange).

    Everything a scheduler asks (usefulness, predicted index, deadline, a window view for
    rollouts) is derived from that state through :func:`advance`.
    """

    spec: RobotSpec
    estimator: DelayEstimator = field(default_factory=DelayEstimator)
    obs_index: int | None = None  # î_j
    obs_anchor: float = 0.0  # server-clock time of the tick at which î_j was observed
    obs_capture_robot: float = 0.0  # the same instant on the robot's clock
    obs_recv: float = 0.0  # server-clock receipt time of that observation
    last_served_index: int | None = None
    queue: list[Chunk] = field(default_factory=list)  # Q_j
    _next_chunk_id: int = 0

    # ---- events ------------------------------------------------------------------------------

    def on_observation(self, index: int, capture_time_robot: float, recv_time: float) -> bool:
        """Record an observation. Returns False (and changes nothing) if it is older than the
        latest one (out-of-order delivery). Raises ValueError if its index goes backwards in time.
        """
        if self.obs_index is not None:
            if capture_time_robot <= self.obs_capture_robot:
                return False
            if index < self.obs_index:
                raise ValueError(
                    f"action index went backwards: {index} after {self.obs_index} "
                    f"(indices only increase when the robot executes)"
                )
        self.obs_index = index
        self.obs_capture_robot = capture_time_robot
        self.obs_anchor = self.estimator.to_server_time(capture_time_robot)
        self.obs_recv = recv_time
        self._prune(index)
        return True

    def on_dispatch(self, t_done: float) -> Chunk:
        """The robot's latest observation goes into a batch that finishes at ``t_done``.

        Returns the chunk entered into ``Q_j`` (``i_start = î_j``, ``h = h_max``, estimated arrival
        ``t_done + d_action``).
        """
        if self.obs_index is None:
            raise ValueError(f"robot {self.spec.robot_id!r} has no observation to serve")
        chunk = Chunk(self._next_chunk_id, self.obs_index, self.spec.h_max, t_done + self.estimator.one_way_s)
        self._next_chunk_id += 1
        self.queue.append(chunk)
        if len(self.queue) > 1 and self.queue[-2].i_start > chunk.i_start:
            self.queue.sort(key=lambda c: (c.i_start, c.chunk_id))
        self.last_served_index = self.obs_index
        return chunk

    def on_cancel(self, chunk: Chunk, previous_last_served: int | None) -> None:
        """A dispatched chunk will never be delivered (its batch failed): forget it, so the robot
        is useful again and the prediction does not count on it."""
        self.queue = [c for c in self.queue if c.chunk_id != chunk.chunk_id]
        if self.last_served_index == chunk.i_start:
            self.last_served_index = previous_last_served

    def on_report(
        self,
        chunk_id: int,
        t_capture_robot: float,
        t_obs_recv: float,
        t_chunk_send: float,
        t_arrival_robot: float,
    ) -> None:
        """The robot reports that chunk ``chunk_id`` (made from the observation captured at
        ``t_capture_robot``, received at ``t_obs_recv`` and answered at ``t_chunk_send`` on the
        server clock) reached it at ``t_arrival_robot`` (robot clock). This is one delay exchange;
        the chunk's arrival is now known exactly and replaces the estimate.
        """
        self.estimator.add_exchange(t_capture_robot, t_obs_recv, t_chunk_send, t_arrival_robot)
        for chunk in self.queue:
            if chunk.chunk_id == chunk_id:
                chunk.t_arrival = self.estimator.to_server_time(t_arrival_robot)
                break

    def _prune(self, index: int) -> None:
        if any(c.end <= index for c in self.queue):
            self.queue = [c for c in self.queue if c.end > index]

    # ---- derived quantities ------------------------------------------------------------------

    def is_useful(self) -> bool:
        """SPEC §3: serving the latest observation now is useful.

        Not useful when there is no observation, when it is the one served last, or when the
        robot executed fewer than ``h_min`` steps since the last served observation.
        """
        return request_is_useful(self.obs_index, self.last_served_index, self.spec.h_min)

    def timeline(self) -> RobotTimeline:
        """A fresh timeline starting at the latest observation (index î_j, at its tick)."""
        return RobotTimeline(self.spec.fps, self.obs_anchor, self.obs_index or 0, 0, list(self.queue))

    def predicted_index(self, now: float) -> int:
        """``i_j``: the index the robot is predicted to hold at ``now`` (before the tick at now)."""
        if self.obs_index is None:
            return 0
        tl = self.timeline()
        tl.run_to(tl.ticks_before(now))
        return tl.index

    def deadline(self) -> float:
        """Server-clock time at which the robot runs dry if no new chunk is generated: the tick
        after the last control step covered by any chunk in ``Q_j`` (EDF's deadline).
        """
        if self.obs_index is None:
            return -math.inf
        tl = self.timeline()
        return tl.tick_time(ticks_until_dry(tl.index, tl.tick_chunks(0)))

    def window_view(self, now: float, window_s: float) -> WindowView:
        """Freeze the mirror at ``now`` for a rollout over ``[now, now + window_s)``."""
        tl = self.timeline()
        start = tl.ticks_before(now)
        tl.run_to(start)
        end = tl.ticks_before(now + window_s)
        return WindowView(self, now, tl.index, tl.tick_time(start), tl.tick_chunks(start), end - start)


def request_is_useful(obs_index: int | None, last_served_index: int | None, h_min: int) -> bool:
    """SPEC §3's usefulness rule, in one place: an observation exists, it is not the one served
    last, and at least ``h_min`` steps were executed since the last served observation."""
    if obs_index is None:
        return False
    if last_served_index is None:
        return True
    steps = obs_index - last_served_index
    return steps > 0 and steps >= h_min


def reward(specs: Sequence[RobotSpec], executed_steps: Sequence[int]) -> float:
    """SPEC §2: weighted executed robot time ``R = Σ_j w_j Δi_j / fps_j`` (seconds)."""
    return sum(s.weight * n / s.fps for s, n in zip(specs, executed_steps, strict=True))
