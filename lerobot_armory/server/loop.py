"""The live serving loop: scheduler decides, engine runs, chunks go out (SPEC §3-§4).

One thread owns the device. Whenever the device is free and some robot has a useful request, it
asks the scheduler for a batch (under the fleet lock, a fraction of a millisecond), takes each
chosen robot's *latest* observation, drops requests that stopped being useful, releases the lock,
runs one batched forward pass, and hands each robot its chunk (tagged with ``i_start``, the index
of the observation it was computed from). Network threads keep feeding observations while the
model runs; they never wait for it and it never waits for them.
"""

from __future__ import annotations

import collections
import inspect
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from lerobot_armory.latency import OnlineLatency
from lerobot_armory.mirror import Chunk
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.schedulers.base import Scheduler, check_batch
from lerobot_armory.server.engine import noise_seed
from lerobot_armory.server.fleet import Fleet, RobotSession
from lerobot_armory.wire import encode

log = logging.getLogger(__name__)

# Warn (once per excursion) when the learnt d_infer moves this far from the start-up profile.
DRIFT_WARN_PCT = 25.0
# This many failed batches in a row, across whichever robots they held, mean the engine is broken,
# not one request: the loop stops and the server exits 1 (a supervisor restarts it) rather than
# failing every robot's every request forever. One failure alone is not enough to tell: a CUDA
# out-of-memory error passes, an illegal memory access does not.
MAX_CONSECUTIVE_FAILURES = 20


class Engine(Protocol):
    """What the loop needs from an engine (``PolicyEngine`` or a test double)."""

    def infer(
        self, observations: Sequence[dict[str, np.ndarray]], tasks: Sequence[str], noise_seeds: Sequence[int] | None = None
    ) -> np.ndarray: ...


def takes_noise_seeds(engine: Engine) -> bool:
    """Whether ``engine.infer`` accepts ``noise_seeds`` (engines written before it existed do not)."""
    try:
        params = inspect.signature(engine.infer).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.name == "noise_seeds" or p.kind is inspect.Parameter.VAR_KEYWORD for p in params) or len(params) >= 3


@dataclass
class WorkItem:
    """One robot's request inside a dispatched batch."""

    session: RobotSession
    observation: dict[str, np.ndarray]
    chunk: Chunk
    previous_last_served: int | None
    capture_robot: float
    obs_recv: float


@dataclass
class BatchRecord:
    """One dispatched batch, for logs, metrics and the benchmark's batch log."""

    t_start: float
    t_end: float
    robots: list[str]
    i_starts: list[int]
    obs_recv: list[float]
    decision_ms: float
    ok: bool = True


@dataclass
class LoopStats:
    """Running counters of the serving loop."""

    batches: int = 0
    failed_batches: int = 0
    batch_sizes: collections.Counter = field(default_factory=collections.Counter)
    infer_ms: dict[int, collections.deque] = field(default_factory=lambda: collections.defaultdict(lambda: collections.deque(maxlen=200)))
    decision_ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=1000))
    # CPU time of the same decisions: the scheduler's own cost, without waits for the GIL or
    # for a core (on a loaded 2-core machine wall time mostly measures those).
    decision_cpu_ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=1000))
    dropped_not_useful: int = 0
    failed_decisions: int = 0  # decisions the scheduler could not make (served in order instead)
    busy_s: float = 0.0
    idle_with_work_s: float = 0.0
    started: float = 0.0


class ServingLoop:
    """Runs the scheduler/engine loop on its own thread until :meth:`stop`.

    Args:
        fleet: the shared fleet state.
        engine: anything with ``infer(observations, tasks) -> (B, H, A)``.
        scheduler: a registered scheduler built for the engine's latency profile.
        on_batch: optional callback with each :class:`BatchRecord` (batch logs).
        latency: if given, every served batch's time feeds this model and its table replaces the
            scheduler's ``d_infer`` whenever it changes (None: the table stays as built).
    """

    def __init__(
        self,
        fleet: Fleet,
        engine: Engine,
        scheduler: Scheduler,
        on_batch: Callable[[BatchRecord], None] | None = None,
        latency: OnlineLatency | None = None,
    ) -> None:
        if latency is not None and latency.max_batch_size != scheduler.max_batch_size:
            raise ValueError(f"latency model covers b <= {latency.max_batch_size}, the scheduler b <= {scheduler.max_batch_size}")
        self.fleet = fleet
        self.engine = engine
        self.scheduler = scheduler
        self.on_batch = on_batch
        self.latency = latency
        self._drift_warned = False
        self._seeds = takes_noise_seeds(engine)
        self._failures_in_a_row = 0
        self.stats = LoopStats(started=fleet.clock())
        self._thread = threading.Thread(target=self._run, name="armory-serving-loop", daemon=True)
        self._last_end: float | None = None
        self._work_at_last_end = False
        self.error: BaseException | None = None

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float | None = None) -> None:
        """Stop after the in-flight batch (its chunks are still delivered)."""
        self.fleet.stop()
        self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        try:
            while True:
                work = self._next_batch()
                if work is None:
                    return
                items, decision_ms = work
                if items:
                    self._serve(items, decision_ms)
        except BaseException as exc:  # pragma: no cover - a bug; logged and surfaced by the server
            self.error = exc
            log.exception("serving loop crashed")
            raise

    def _next_batch(self) -> tuple[list[WorkItem], float] | None:
        fleet = self.fleet
        with fleet.cond:
            while True:
                if fleet.stopping:
                    return None
                now = fleet.clock()
                # A robot over its granted share of device time waits until the share decays.
                sessions = [s for s in fleet.active() if not fleet.over_share(s, now)]
                if any(s.mirror.is_useful() for s in sessions):
                    break
                fleet.cond.wait(0.05 if len(sessions) < len(fleet.active()) else 0.25)
            if self._last_end is not None and self._work_at_last_end:
                self.stats.idle_with_work_s += max(0.0, now - self._last_end)
            t0, c0 = time.perf_counter(), time.thread_time()
            chosen = self._select(sessions, now)
            decision_ms = (time.perf_counter() - t0) * 1000.0
            self.stats.decision_ms.append(decision_ms)
            self.stats.decision_cpu_ms.append((time.thread_time() - c0) * 1000.0)
            t_done_estimate = now + self.scheduler.d_infer[len(chosen) - 1] if chosen else now
            items = []
            for session in chosen:
                mirror = session.mirror
                # The latest observation is read now; a request that stopped being useful since
                # the decision (cannot happen under this lock, but the rule is the engine's) is dropped.
                if session.latest is None or not mirror.is_useful():
                    self.stats.dropped_not_useful += 1
                    continue
                previous = mirror.last_served_index
                chunk = mirror.on_dispatch(t_done_estimate)
                items.append(WorkItem(session, session.latest, chunk, previous, mirror.obs_capture_robot, mirror.obs_recv))
            return items, decision_ms

    def _select(self, sessions: list[RobotSession], now: float) -> list[RobotSession]:
        """The scheduler's batch as sessions. Whatever a robot sent, a failing decision never
        stops the loop: the robots whose mirror cannot be evaluated are dropped (told why) and the
        decision is retried; if it still fails, the first useful robots are served in order."""
        for attempt in range(2):
            try:
                chosen = self.scheduler.select([s.mirror for s in sessions], now)
                check_batch(chosen, self.scheduler.max_batch_size, type(self.scheduler).__name__)
                by_mirror = {id(s.mirror): s for s in sessions}
                return [by_mirror[id(m)] for m in chosen]
            except Exception as exc:  # noqa: BLE001 - isolated below; the loop must go on
                error = exc
                if attempt == 0:
                    sessions = self._quarantine_broken(sessions, now)
        self.stats.failed_decisions += 1
        log.error("%s failed to decide (%s: %s); serving the first useful robots in order", type(self.scheduler).__name__,
                  type(error).__name__, error)  # fmt: skip
        return [s for s in sessions if s.mirror.is_useful()][: self.scheduler.max_batch_size]

    def _quarantine_broken(self, sessions: list[RobotSession], now: float) -> list[RobotSession]:
        """Evaluate every mirror the way schedulers do; drop the robots whose mirror raises."""
        kept = []
        for session in sessions:
            mirror = session.mirror
            try:
                mirror.deadline()
                mirror.predicted_index(now)
                mirror.window_view(now, 1.0).executed()
            except Exception as exc:  # noqa: BLE001 - this robot's state is broken, not the loop
                log.error("dropping robot %s: its state cannot be scheduled (%s: %s)", session.robot_id, type(exc).__name__, exc)
                self.fleet.quarantine(session, f"your session was ended: the server cannot schedule your state ({type(exc).__name__})")
                continue
            kept.append(session)
        return kept

    def _serve(self, items: list[WorkItem], decision_ms: float) -> None:
        fleet = self.fleet
        t_start = fleet.clock()
        try:
            observations, tasks = [it.observation for it in items], [it.session.task for it in items]
            if self._seeds:
                actions = self.engine.infer(observations, tasks, [noise_seed(it.session.robot_id, it.chunk.chunk_id) for it in items])
            else:
                actions = self.engine.infer(observations, tasks)
            if actions.shape[0] != len(items):
                raise RuntimeError(f"engine returned {actions.shape[0]} chunks for a batch of {len(items)}")
        except Exception as exc:
            self._fail(items, exc, t_start, decision_ms)
            return
        t_done = fleet.clock()
        self._failures_in_a_row = 0
        size = len(items)
        with fleet.cond:
            for k, it in enumerate(items):
                session = it.session
                if fleet.sessions.get(session.session_id) is not session:
                    continue  # the robot left while its batch ran: its chunk goes nowhere
                # The chunk's real completion time replaces the estimate used at dispatch.
                it.chunk.t_arrival = t_done + session.mirror.estimator.one_way_s
                msg = pb.ServerMessage(
                    chunk=pb.ActionChunk(
                        chunk_id=it.chunk.chunk_id,
                        i_start=it.chunk.i_start,
                        actions=encode("action", np.ascontiguousarray(actions[k], dtype=np.float32)),
                        server_send_time=t_done,
                        obs_capture_time=it.capture_robot,
                    )
                )
                fleet.record_sent(session, it.chunk, it.capture_robot, it.obs_recv, t_done)
                session.outbox.put(msg)
            fleet.charge_device([it.session for it in items], t_done - t_start, t_done)
            self._finish(size, t_start, t_done)
            fleet.cond.notify_all()
        if self.latency is not None:
            self._learn(size, t_done - t_start)
        self._record(items, t_start, t_done, decision_ms, ok=True)

    def _learn(self, size: int, seconds: float) -> None:
        """Feed one served batch to the latency model; hand a changed table to the scheduler.

        Failed batches are not fed: an exception's timing says nothing about inference.
        """
        model = self.latency
        assert model is not None
        if not model.observe(size, seconds):
            return  # the published table did not move: the scheduler keeps its list untouched
        table = model.table_s()
        with self.fleet.cond:
            # In place, under the lock every decision holds: schedulers read self.d_infer on each
            # decision (some keep a local alias for its duration), and none sees a half-written table.
            self.scheduler.d_infer[:] = table
        worst = model.max_drift()
        if abs(worst.pct) > DRIFT_WARN_PCT and not self._drift_warned:
            self._drift_warned = True
            log.warning(
                "d_infer drifted %+.0f%% from the start-up profile at b=%d (%.1f -> %.1f ms); the scheduler now uses "
                "the measured table: %s ms",
                worst.pct, worst.batch_size, worst.startup_ms, worst.current_ms, ", ".join(f"{ms:.1f}" for ms in model.table_ms()),
            )  # fmt: skip
        elif abs(worst.pct) < DRIFT_WARN_PCT / 2:
            self._drift_warned = False  # back near the profile: warn again on the next excursion

    def _fail(self, items: list[WorkItem], exc: Exception, t_start: float, decision_ms: float) -> None:
        """An engine error hurts only this batch: its robots are told and become useful again."""
        log.error("inference failed for a batch of %d (%s): %s", len(items), ", ".join(it.session.robot_id for it in items), exc)
        t_end = self.fleet.clock()
        with self.fleet.cond:
            for it in items:
                it.session.mirror.on_cancel(it.chunk, it.previous_last_served)
                it.session.outbox.put(
                    pb.ServerMessage(
                        notice=pb.Notice(
                            kind=pb.Notice.INFERENCE_FAILED,
                            message=f"inference failed for this batch ({type(exc).__name__}: {exc}); your next observation will be served",
                            index=it.chunk.i_start,
                        )
                    )
                )
            self.stats.failed_batches += 1
            self._finish(len(items), t_start, t_end)
            self.fleet.cond.notify_all()
        self._record(items, t_start, t_end, decision_ms, ok=False)
        self._failures_in_a_row += 1
        if self._failures_in_a_row >= MAX_CONSECUTIVE_FAILURES:
            # A sticky device error (an illegal memory access leaves the CUDA context unusable) fails
            # every batch in quick succession and lands here within a second or so.
            self.error = RuntimeError(
                f"the engine is broken ({self._failures_in_a_row} failed batches in a row; last: {type(exc).__name__}: {exc})"
            )
            log.error("stopping: %s", self.error)
            self.fleet.stop()  # the loop ends at its next decision; the server sees loop.error and exits 1

    def _finish(self, size: int, t_start: float, t_end: float) -> None:
        """Counters at the end of a batch (lock held)."""
        self.stats.batches += 1
        self.stats.batch_sizes[size] += 1
        self.stats.infer_ms[size].append((t_end - t_start) * 1000.0)
        self.stats.busy_s += t_end - t_start
        self._last_end = t_end
        self._work_at_last_end = any(s.mirror.is_useful() for s in self.fleet.active())

    def _record(self, items: list[WorkItem], t_start: float, t_end: float, decision_ms: float, ok: bool) -> None:
        if self.on_batch is not None:
            self.on_batch(
                BatchRecord(
                    t_start,
                    t_end,
                    [it.session.robot_id for it in items],
                    [it.chunk.i_start for it in items],
                    [it.obs_recv for it in items],
                    decision_ms,
                    ok,
                )
            )
