"""The chunk mirror: robot specs, chunk queues, delay estimates and *the* transition (docs/spec.md §2).

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

import bisect
import math
import numbers
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from lerobot_armory.errors import ConfigError

# Tolerance when mapping a time onto the tick grid: a chunk that arrives exactly at a tick
# (t_arrival == tick time, up to float rounding) counts as arrived at that tick (SPEC: t_arrival
# <= tick time).
_EPS = 1e-9
# Slack on offsets and times for float rounding and scheduling noise (seconds).
_OFFSET_TOLERANCE_S = 0.005

TIERS = ("fast", "slow")
# Longest robot id: ids travel in every log line, metric label and status row.
MAX_ROBOT_ID = 128

# Physical bounds of a robot's declared rates: beyond them no controller exists and the tick
# arithmetic (1 / fps, ticks * fps) leaves the floats (fps = 1e308 made ``math.ceil`` raise).
MIN_FPS = 0.01
MAX_FPS = 1000.0
MAX_WEIGHT = 1e6

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
# Progress bound (RobotMirror.progress_bound): a robot cannot execute an action before the chunk
# holding it left the server, and executes at most fps actions a second. No slack for ticks: an
# observation is captured at a tick, before that tick's action, so the actions it counts were all
# executed at ticks strictly between the chunk's arrival and the capture. A robot's clock (and so
# its rate) may run fast by a crystal's error (tens of ppm); more tolerance would let a liar's
# claims drift ahead of any honest robot's for as long as it never runs dry (2 % measured +18-24 %
# chunks/s in a saturated fleet).
PROGRESS_SLACK_STEPS = 0.0
FPS_TOLERANCE = 0.001
# Sent chunks whose arrival report the mirror still awaits. A robot reports within a second or so
# (several chunks); one that never reports must not grow the table, so the oldest are forgotten.
MAX_AWAITING_REPORTS = 64
# An episode boundary (a reset world) makes a robot's next observation worth serving at once, not
# h_min steps later. Honest episodes last seconds; a robot that claims a boundary every tick would
# be served every batch, so boundaries make it useful at most once per h_min ticks of server time.


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

    Raises:
        ConfigError: naming every problem :func:`spec_problems` finds (``field`` is the first's).
    """

    robot_id: str
    fps: float
    chunk_size: int
    h_min: int
    h_max: int
    weight: float = 1.0
    tier: str = "slow"

    def __post_init__(self) -> None:
        problems = spec_problems(self.robot_id, self.fps, self.chunk_size, self.h_min, self.h_max, self.weight, self.tier)
        if problems:
            raise ConfigError.listing(problems)


def _shown(value: object, limit: int = 40) -> str:
    """``repr(value)``, cut short: values may come from the wire, and an error echoes them."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _is_real(value: object) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_int(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def spec_problems(
    robot_id: str, fps: float, chunk_size: int | None, h_min: int, h_max: int, weight: float, tier: str
) -> list[str]:
    """Every problem of a robot's declared spec, as ``field: why`` strings (empty: valid).

    The one validator of what a robot declares: :class:`RobotSpec` raises with it, the server
    answers a registration with it and the client command line checks its flags with it, so the
    three agree, and each names every problem at once rather than the first.

    Values may come straight from the wire or a command line, so a value of the wrong type (a
    string fps, a float horizon) is a problem, never an exception. ``chunk_size`` None means not known yet (a robot learns the
    policy's H only when it registers): the checks that need it are left to the server.
    A relation (``h_min <= h_max <= H``) is checked only when its fields are valid on their own,
    so one bad value is named once.
    """
    problems = []
    if not (isinstance(robot_id, str) and 0 < len(robot_id) <= MAX_ROBOT_ID and robot_id.isprintable()):
        problems.append(f"robot_id: must be a non-empty string of at most {MAX_ROBOT_ID} printable characters")
    if not (_is_real(fps) and MIN_FPS <= fps <= MAX_FPS):  # NaN fails the comparison
        problems.append(f"fps: must be a number of steps per second in [{MIN_FPS:g}, {MAX_FPS:g}], got {_shown(fps)}")
    chunk_ok = chunk_size is None or (_is_int(chunk_size) and chunk_size >= 1)
    if not chunk_ok:
        problems.append(f"chunk_size: must be an integer >= 1, got {_shown(chunk_size)}")
    h_min_ok = _is_int(h_min) and h_min >= 0
    if not h_min_ok:
        problems.append(f"h_min: must be an integer >= 0, got {_shown(h_min)}")
    h_max_ok = _is_int(h_max) and h_max >= 1
    if not h_max_ok:
        problems.append(f"h_max: must be an integer >= 1, got {_shown(h_max)}")
    if h_min_ok and h_max_ok and h_min > h_max:
        problems.append(f"h_min: h_min={h_min} is larger than h_max={h_max}")
    if h_max_ok and chunk_ok and chunk_size is not None and h_max > chunk_size:
        problems.append(f"h_max: h_max={h_max} is larger than the chunk size H={chunk_size}")
    if not (_is_real(weight) and 0 < weight <= MAX_WEIGHT):
        problems.append(f"weight: must be a positive number up to {MAX_WEIGHT:g}, got {_shown(weight)}")
    if not (isinstance(tier, str) and tier in TIERS):
        problems.append(f"tier: must be one of {', '.join(TIERS)}, got {_shown(tier)}")
    return problems


@dataclass(slots=True)
class Chunk:
    """A chunk generated for one robot: actions for indices ``[i_start, i_start + h)``.

    ``t_arrival`` is in the clock of the timeline that owns the chunk: the server's estimate of
    when the robot will hold it (mirror), or the true arrival time (simulated ground truth).
    A chunk still in inference or on the network is simply one whose arrival is in the future.

    A mirror's chunk also keeps the three server-side stamps of its delay exchange (docs/spec.md §2):
    when its observation was captured (robot clock) and received, and when the chunk was sent.
    They stay inside the mirror until the robot reports the chunk's arrival (NaN elsewhere).
    """

    chunk_id: int
    i_start: int
    h: int
    t_arrival: float
    capture_robot: float = math.nan
    obs_recv: float = math.nan
    t_sent: float = math.nan
    episode: int = 0  # the episode of the observation it was computed from

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


def observed_tick(t: float, origin: float, fps: float, one_way_s: float) -> int:
    """Tick (counted from the tick at ``origin``) whose observation is the latest the server
    holds at ``t``: the robot sends at every tick and the observation takes ``one_way_s`` to
    arrive. Negative when none of this grid's observations has arrived by ``t``."""
    return math.floor((t - one_way_s - origin) * fps + _EPS)


# --------------------------------------------------------------------------------------------
# The transition on a coverage queue (the form the schedulers' rollouts use)
#
# A chunk made from one of the robot's observations starts at or before the index the robot
# holds when the chunk arrives, so what the robot can execute is always one stretch
# ``[index, coverage end)`` that each arrival extends. A :data:`Queue` keeps a robot that way --
# ``(coverage end at tick 0, pending (arrival tick, end) sorted)`` -- and the functions below
# answer "index at a tick", "when does it run dry", "when does it reach an index" in a loop over
# the few pending arrivals. They are :func:`advance` specialised to such chunk sets (property-
# tested against it in ``tests/core/test_mirror.py``), not a second transition.

Queue = tuple[int, tuple[tuple[int, int], ...]]


def queue_of(index: int, chunks: Sequence[TickChunk]) -> Queue:
    """The queue form of a robot's chunks on a grid where ``index`` is held before tick 0.

    Valid for chunks that start at or before the index the robot holds when they arrive (every
    chunk made from one of the robot's observations does). Chunks that arrived by tick 0 give
    the coverage end; the others are kept as ``(arrival tick, end)``.
    """
    end0 = reach(index, chunks, 0)
    pending = sorted((a, e) for _, e, a in chunks if a > 0 and e > index)
    return end0, tuple(pending)


def queue_with(queue: Queue, arrival: int, end: int) -> Queue:
    """``queue`` with one more chunk covering up to ``end`` from tick ``arrival``."""
    end0, pending = queue
    if arrival <= 0:
        return max(end0, end), pending
    return end0, tuple(sorted((*pending, (arrival, end))))


def index_at(index: int, queue: Queue, tick: int) -> int:
    """Index held before ``tick`` (ticks ``0 .. tick-1`` run): one step per tick while the
    coverage lasts; an arrival extends the coverage (equals :func:`advance`)."""
    end, pending = queue
    x, at = index, 0
    # min() spelled as conditionals: these loops are the schedulers' hot path.
    for a, e in pending:
        if a > tick:
            break
        x += a - at
        if x > end:
            x = end
        at = a
        if e > end:
            end = e
    x += tick - at
    return x if x < end else end


def dry_tick(index: int, queue: Queue) -> int:
    """Tick at which the robot starves once every pending chunk has arrived (EDF's deadline;
    :func:`ticks_until_dry` also waits for chunks that land after the robot passed their end)."""
    end, pending = queue
    x, at = index, 0
    for a, e in pending:
        x += a - at
        if x > end:
            x = end
        at = a
        if e > end:
            end = e
    return at + end - x


def tick_reaching(index: int, queue: Queue, target: int) -> int:
    """First tick before which the robot holds an index >= ``target`` (-1 if it never does)."""
    end, pending = queue
    x, at = index, 0
    if x >= target:
        return 0
    for a, e in pending:
        if end >= target and x + a - at >= target:
            return at + target - x
        x += a - at
        if x > end:
            x = end
        at = a
        if e > end:
            end = e
    return at + target - x if end >= target else -1


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
        if abs(offset - self.offset_s) > (rtt + self.round_trip_s) / 2.0 + _OFFSET_TOLERANCE_S:
            self.outliers += 1
            pending = self._pending
            if pending and abs(offset - pending[-1]) > rtt + _OFFSET_TOLERANCE_S:
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


@dataclass(frozen=True)
class ExecutionPrefix:
    """What a robot executes from a booked chunk's first index on, as its mirror predicts it
    (real-time chunking's two inputs, docs/spec.md §2 applied to one request).

    Attributes:
        inference_delay: steps the robot executes (from older chunks) before the booked chunk
            arrives; its first executed action is this one.
        segments: ``(chunk_id, offset, count)`` in index order from the booked chunk's
            ``i_start``: the robot executes ``count`` actions of chunk ``chunk_id`` from
            ``offset`` on, had the booked chunk never come. Ends where the robot would run dry
            (or after one chunk length). A robot already dry at ``i_start`` executes nothing:
            then the one segment is ``(chunk it ran out of, offset at i_start, 0)``, whose
            actions past ``h_max`` the policy planned but the robot never executes.
    """

    inference_delay: int
    segments: tuple[tuple[int, int, int], ...]

    @property
    def length(self) -> int:
        return sum(n for _, _, n in self.segments)


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
    """The server's model of one robot (docs/spec.md §2): ``i_j``, ``î_j``, ``Q_j`` and delay estimates.

    Fed by three events, each with the time it happened on the server clock:

    - :meth:`on_observation`: an observation with index ``î`` captured at a robot-clock time;
    - :meth:`on_dispatch` / :meth:`on_complete` / :meth:`on_cancel`: a batch containing this
      robot is planned to finish at ``t_done``, finished (the chunk was sent), or failed;
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
    clock_faults: int = 0  # implausible robot times in a row (reset by a plausible one)
    needs_sync: bool = False  # the clock looked stepped: the owner should request a fresh exchange
    clamped_indices: int = 0  # observations whose claimed index ran ahead of what the server saw
    _next_chunk_id: int = 0
    _awaiting: dict[int, Chunk] = field(default_factory=dict)  # sent chunks not yet reported, by id
    # The progress bound: the robot's index was at most _bound at server time _bound_t, holding _held
    # ((start, end) spans sent to it); finished chunks wait in _unheld until the bound reaches them.
    _bound: float | None = None
    _bound_t: float = 0.0
    _held: list[TickChunk] = field(default_factory=list)  # sorted by start, arrival tick 0
    _unheld: list[Chunk] = field(default_factory=list)
    _in_flight: dict[int, Chunk] = field(default_factory=dict)  # dispatched, batch not finished
    ran_out: Chunk | None = None  # the newest chunk the robot ran past (RTC continues its plan)
    episode: int = 0  # the robot's current episode (its latest observation's)
    episodes_started: int = 0  # boundaries seen (a new episode after the first observation)
    _episode_due: float | None = None  # server time from which a pending boundary makes the robot useful
    _last_boundary: float = -math.inf  # server time the last boundary made the robot useful

    # ---- events ------------------------------------------------------------------------------

    def on_observation(self, index: int, capture_time_robot: float, recv_time: float, episode: int = 0) -> bool:
        """Record an observation. Returns False (and changes nothing) if it is older than the
        latest one (out-of-order delivery). Raises ValueError if its index or episode goes
        backwards in time or a time is not finite.

        A higher ``episode`` than the latest is an episode boundary (see :meth:`_begin_episode`):
        every chunk booked so far is void, and the robot is served again without waiting for
        ``h_min`` executed steps.

        Nothing the robot claims is taken beyond what the server itself saw (docs/spec.md §2, edge
        checks): the capture instant is placed at most ``uplink_window_s`` before its receipt
        (an implausible one counts as a clock fault, and ``CLOCK_FAULTS_FOR_STEP`` in a row
        restart the clock offset and raise ``needs_sync``), and the index is capped by the chunks
        sent to the robot and the times they left the server (:meth:`progress_bound`), so an
        index or a clock that runs ahead buys nothing.
        """
        if not (math.isfinite(capture_time_robot) and math.isfinite(recv_time)):
            raise ValueError("capture time is not a finite number")
        if self.obs_index is not None:
            if capture_time_robot > self.obs_capture_robot:
                if index < self.obs_index:
                    raise ValueError(
                        f"action index went backwards: {index} after {self.obs_index} "
                        f"(indices only increase when the robot executes)"
                    )
                if episode < self.episode:
                    raise ValueError(f"episode went backwards: {episode} after {self.episode} (episodes only increase)")
            else:
                # Not newer: a reordered observation (drop it), unless it is far older than jitter
                # explains, which is the robot's clock stepping back: after a run of those the
                # offset restarts and the observation is taken.
                if self.obs_capture_robot - capture_time_robot <= REORDER_WINDOW_S or index < self.obs_index:
                    return False
                if not self._clock_fault(capture_time_robot, recv_time):
                    return False
        elif episode < 0:
            raise ValueError(f"episode must be >= 0, got {episode}")
        index = self._bounded_index(index, recv_time)
        if episode > self.episode:
            self._begin_episode(episode, recv_time, first=self.obs_index is None)
        self.obs_index = index
        self.obs_capture_robot = capture_time_robot
        self.obs_anchor = self._anchor(capture_time_robot, recv_time)
        self.obs_recv = recv_time
        self._prune(index)
        if self._episode_due is not None and recv_time >= self._episode_due:
            self._episode_due = None
            self.last_served_index = None  # useful now: the robot holds nothing of this episode
        return True

    def _begin_episode(self, episode: int, recv: float, first: bool) -> None:
        """The robot reset its world: nothing booked for the old episode will be executed.

        The queue empties (the prediction counts on no old chunk; a chunk still in flight is
        delivered tagged with its old episode and dropped by the robot), RTC continues no old
        plan, and the robot becomes useful at once, or once ``h_min`` ticks passed since the last
        boundary did (a robot claiming boundaries every tick is not served every batch).
        """
        self.episode = episode
        if first:
            return  # a robot that registers mid-run: its first observation is useful anyway
        self.episodes_started += 1
        self.queue = []
        self.ran_out = None
        if self._episode_due is None:  # a boundary already pending keeps its time
            self._episode_due = max(recv, self._last_boundary + self.spec.h_min / self.spec.fps)
            self._last_boundary = self._episode_due

    def _anchor(self, capture_robot: float, recv: float) -> float:
        """The capture instant on the server clock, inside ``[recv - window, recv]``."""
        est = self.estimator
        anchor = est.to_server_time(capture_robot)
        window = est.uplink_window_s()
        if recv - window - _OFFSET_TOLERANCE_S <= anchor <= recv + est.round_trip_s + _OFFSET_TOLERANCE_S:
            self.clock_faults = 0
            return min(recv, max(recv - window, anchor))
        self._clock_fault(capture_robot, recv)
        return recv - est.one_way_s  # the server's own estimate (equal to the above after a restart)

    def _clock_fault(self, t_robot: float, recv: float) -> bool:
        """A robot time the server cannot believe. A run of them means the robot's clock stepped
        (or lies): restart the offset from this message and ask for a fresh exchange (returns True)."""
        self.clock_faults += 1
        if self.clock_faults < CLOCK_FAULTS_FOR_STEP:
            return False
        self.estimator.restart(t_robot, recv)
        self.clock_faults = 0
        self.needs_sync = True
        return True

    def _bounded_index(self, claimed: int, recv: float) -> int:
        """The claimed index, capped by :meth:`progress_bound` (see :meth:`on_observation`)."""
        if self._bound is None:  # the first observation starts the bound
            self._bound, self._bound_t = float(claimed), recv
            return claimed
        bound = self.progress_bound(recv)
        floor = math.floor(bound + _EPS)
        cap = min(math.floor(bound + PROGRESS_SLACK_STEPS + _EPS), max(floor, reach(floor, self._held, 0)))
        cap = max(self.obs_index or 0, cap)
        if claimed > cap:
            self.clamped_indices += 1
            return cap
        return claimed

    def progress_bound(self, now: float) -> float:
        """The highest index the robot can have reached by ``now`` (server clock): the index of a
        robot with no network delay that executed every action as soon as it could.

        From the first observation on, the bound runs at the declared fps (``FPS_TOLERANCE`` more)
        but never past the end of the actions sent so far, each usable only once its chunk left
        the server. An honest robot receives a chunk after it is sent and executes at most one
        action a tick, so its index never exceeds the bound (by more than the one action of
        ``PROGRESS_SLACK_STEPS``); a robot that claims it executed everything it holds looks
        exactly like that best-case honest robot, never one that ran ahead of its deliveries.
        Advancing is monotone in ``now`` (an earlier ``now`` than the last one returns the bound
        as it stands).
        """
        assert self._bound is not None
        rate = self.spec.fps * (1.0 + FPS_TOLERANCE)
        u, t = self._bound, self._bound_t
        if now <= t:
            return u
        ready = sorted((c for c in self._unheld if c.t_sent <= now), key=lambda c: (c.t_sent, c.chunk_id))
        for c in [*ready, None]:
            t_next = now if c is None else max(t, c.t_sent)
            covered = reach(math.floor(u + _EPS), self._held, 0)
            u = min(u + (t_next - t) * rate, max(u, float(covered)))
            t = t_next
            if c is not None:
                bisect.insort(self._held, (c.i_start, c.end, 0))
        if ready:
            taken = {c.chunk_id for c in ready}
            self._unheld = [c for c in self._unheld if c.chunk_id not in taken]
        floor = math.floor(u + _EPS)
        self._held = [h for h in self._held if h[1] > floor]
        self._bound, self._bound_t = u, now
        return u

    def progress_wait_s(self, index: int, now: float) -> float:
        """Seconds from ``now`` until :meth:`progress_bound` allows ``index``: 0 if it does now,
        ``inf`` if the chunks sent do not reach it. For a server-side model of a robot that asks
        for its next chunk after a fixed number of actions (openpi's clients)."""
        if self._bound is None:
            return 0.0
        u = self.progress_bound(now)
        floor = math.floor(u + _EPS)
        if index <= floor:
            return 0.0
        if index > reach(floor, self._held, 0):
            return math.inf
        return (index - u) / (self.spec.fps * (1.0 + FPS_TOLERANCE))

    def on_dispatch(self, t_done: float) -> Chunk:
        """The robot's latest observation goes into a batch predicted to finish at ``t_done``.

        Returns the chunk entered into ``Q_j`` (``i_start = î_j``, ``h = h_max``, arrival
        predicted by :meth:`_arrival`). Drivers call this through
        :meth:`lerobot_armory.dispatch.Dispatcher.plan`, never directly.
        """
        if self.obs_index is None:
            raise ValueError(f"robot {self.spec.robot_id!r} has no observation to serve")
        chunk = Chunk(
            self._next_chunk_id, self.obs_index, self.spec.h_max, math.nan, self.obs_capture_robot, self.obs_recv, episode=self.episode
        )
        self._next_chunk_id += 1
        self._sent(chunk, t_done)
        self.queue.append(chunk)
        if len(self.queue) > 1 and self.queue[-2].i_start > chunk.i_start:
            self.queue.sort(key=lambda c: (c.i_start, c.chunk_id))
        self.last_served_index = self.obs_index
        self._in_flight[chunk.chunk_id] = chunk
        self._awaiting[chunk.chunk_id] = chunk
        while len(self._awaiting) > MAX_AWAITING_REPORTS:
            self._awaiting.pop(next(iter(self._awaiting)))
        return chunk

    def on_complete(self, chunk: Chunk, t_done: float) -> None:
        """The chunk's batch really finished (and the chunk was sent) at ``t_done``: the actual
        time replaces the prediction made at dispatch."""
        if self._in_flight.pop(chunk.chunk_id, None) is not None:
            self._unheld.append(chunk)
        self._sent(chunk, t_done)

    def _sent(self, chunk: Chunk, t_send: float) -> None:
        """THE place a chunk's arrival is predicted: sent at ``t_send``, it reaches the robot one
        estimated one-way delay later (until the robot's report says when it really did)."""
        chunk.t_sent = t_send
        chunk.t_arrival = t_send + self.estimator.one_way_s

    def on_cancel(self, chunk: Chunk, previous_last_served: int | None) -> None:
        """A dispatched chunk will never be delivered (its batch failed): forget it, so the robot
        is useful again and the prediction does not count on it."""
        self.queue = [c for c in self.queue if c.chunk_id != chunk.chunk_id]
        self._in_flight.pop(chunk.chunk_id, None)
        self._awaiting.pop(chunk.chunk_id, None)
        if self.last_served_index == chunk.i_start:
            self.last_served_index = previous_last_served

    def on_report(self, chunk_id: int, t_arrival_robot: float, t_report_recv: float = math.inf) -> bool | None:
        """The robot reports that chunk ``chunk_id`` reached it at ``t_arrival_robot`` (robot
        clock); the report reached the server at ``t_report_recv``. With the chunk's own stamps
        (its observation's capture and receipt, its sending) this is one delay exchange, and the
        chunk's arrival is now known and replaces the prediction.

        The arrival is believed only between the chunk's sending and the report's receipt: a
        chunk cannot arrive before it left, nor be reported before it arrived. Returns None for
        a chunk the mirror does not await (unknown, already reported, or forgotten), False when
        the exchange was refused as implausible, True otherwise.
        """
        chunk = self._awaiting.pop(chunk_id, None)
        if chunk is None:
            return None
        verdict = self.estimator.add_exchange(chunk.capture_robot, chunk.obs_recv, chunk.t_sent, t_arrival_robot)
        if verdict == "refused":
            return False
        arrival = self.estimator.to_server_time(t_arrival_robot)
        chunk.t_arrival = min(max(arrival, chunk.t_sent), t_report_recv)
        return verdict != "outlier"

    def _prune(self, index: int) -> None:
        if any(c.end <= index for c in self.queue):
            for c in self.queue:
                if c.end <= index and (self.ran_out is None or (c.i_start, c.chunk_id) > (self.ran_out.i_start, self.ran_out.chunk_id)):
                    self.ran_out = c
            self.queue = [c for c in self.queue if c.end > index]

    # ---- derived quantities ------------------------------------------------------------------

    def is_useful(self) -> bool:
        """docs/spec.md §3: serving the latest observation now is useful.

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

    def prefix_of(self, chunk: Chunk) -> ExecutionPrefix | None:
        """What the robot executes from ``chunk.i_start`` on while ``chunk`` (booked by the last
        dispatch, still from the latest observation) is computed and sent, through
        :func:`advance` (the chunks switched to, with the delay until ``chunk`` arrives).
        None when the robot would execute nothing of another chunk from there.
        """
        if self.obs_index is None or chunk.i_start != self.obs_index:
            raise ValueError("a prefix is taken right after its chunk was booked from the latest observation")
        tl = RobotTimeline(self.spec.fps, self.obs_anchor, self.obs_index, 0, [c for c in self.queue if c.chunk_id != chunk.chunk_id])
        ticks = tl.tick_chunks(0)
        arrival = max(0, tick_of(chunk.t_arrival, self.obs_anchor, self.spec.fps))
        delay = advance(self.obs_index, ticks, arrival) - self.obs_index
        uses: list[tuple[int, int]] = []
        end = advance(self.obs_index, ticks, ticks_until_dry(self.obs_index, ticks), lambda pos, off: uses.append((pos, off)))
        end = min(end, chunk.i_start + chunk.h)
        segments = []
        for k, (pos, offset) in enumerate(uses):
            used = tl.chunks[pos]
            start = used.i_start + offset
            stop = min(end, tl.chunks[uses[k + 1][0]].i_start + uses[k + 1][1]) if k + 1 < len(uses) else end
            if stop > start:
                segments.append((used.chunk_id, offset, stop - start))
        if not segments and self.ran_out is not None and self.ran_out.chunk_id != chunk.chunk_id:
            segments.append((self.ran_out.chunk_id, chunk.i_start - self.ran_out.i_start, 0))
        return ExecutionPrefix(delay, tuple(segments)) if segments else None

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
    """docs/spec.md §3's usefulness rule, in one place: an observation exists, it is not the one served
    last, and at least ``h_min`` steps were executed since the last served observation."""
    if obs_index is None:
        return False
    if last_served_index is None:
        return True
    steps = obs_index - last_served_index
    return steps > 0 and steps >= h_min


def reward(specs: Sequence[RobotSpec], executed_steps: Sequence[int]) -> float:
    """docs/spec.md §2: weighted executed robot time ``R = Σ_j w_j Δi_j / fps_j`` (seconds)."""
    return sum(s.weight * n / s.fps for s, n in zip(specs, executed_steps, strict=True))
