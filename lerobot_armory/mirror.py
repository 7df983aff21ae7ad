"""The chunk mirror: the server's prediction of each robot's queue (:class:`RobotMirror`) and the
simulator's ground truth (:class:`RobotTimeline`), both moved by the one transition of
:mod:`lerobot_armory.transition` (docs/spec.md §2).

Everything here is pure and deterministic: no I/O, no threads, no clock reads. Time is always
passed in, so the live server drives these objects with wall time and the simulator drives the
very same objects with simulated time ("one mirror, two clocks"). The robot's declaration lives in
:mod:`lerobot_armory.robot_spec`, clock-offset estimation in :mod:`lerobot_armory.delay`.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from lerobot_armory.delay import CLOCK_FAULTS_FOR_STEP, OFFSET_TOLERANCE_S, REORDER_WINDOW_S, DelayEstimator
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.transition import TICK_EPS, Chunk, TickChunk, advance, reach, tick_of, ticks_until_dry

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
        if recv - window - OFFSET_TOLERANCE_S <= anchor <= recv + est.round_trip_s + OFFSET_TOLERANCE_S:
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
        floor = math.floor(bound + TICK_EPS)
        cap = min(math.floor(bound + PROGRESS_SLACK_STEPS + TICK_EPS), max(floor, reach(floor, self._held, 0)))
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
            covered = reach(math.floor(u + TICK_EPS), self._held, 0)
            u = min(u + (t_next - t) * rate, max(u, float(covered)))
            t = t_next
            if c is not None:
                bisect.insort(self._held, (c.i_start, c.end, 0))
        if ready:
            taken = {c.chunk_id for c in ready}
            self._unheld = [c for c in self._unheld if c.chunk_id not in taken]
        floor = math.floor(u + TICK_EPS)
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
        floor = math.floor(u + TICK_EPS)
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
