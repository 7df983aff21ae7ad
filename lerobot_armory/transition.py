"""Chunks on a robot's tick grid and *the* transition (docs/spec.md §2).

Time model. A robot ticks at ``fps``. At every tick it first captures and sends its observation
(tagged with its current action index ``i``), then executes action ``i`` iff some *arrived* chunk
covers ``i`` (``i_start <= i < i_start + h``) and advances ``i <- i + 1``; otherwise it starves and
``i`` stays. Ticks are counted on an integer grid from an *anchor* (a time at which a tick
happens), so a chunk's arrival becomes the first tick at or after its arrival time. Working on
integer ticks keeps the transition exact (no float drift over a 5-minute run) and lets it skip
whole runs of ticks at once, which is what makes Lookahead fast enough to search online.

The single transition is :func:`advance`. The robot's ground truth in the simulator
(:class:`~lerobot_armory.mirror.RobotTimeline`) and the server's prediction
(:class:`~lerobot_armory.mirror.RobotMirror`) both call it; the coverage-queue functions below are
it specialised, not a second one. Pure: no I/O, no clock reads.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass


# Tolerance when mapping a time onto the tick grid: a chunk that arrives exactly at a tick
# (t_arrival == tick time, up to float rounding) counts as arrived at that tick (SPEC: t_arrival
# <= tick time).
TICK_EPS = 1e-9



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
    return math.ceil((t - anchor) * fps - TICK_EPS)


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
    return math.floor((t - one_way_s - origin) * fps + TICK_EPS)


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

