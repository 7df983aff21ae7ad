"""The live serving loop: scheduler decides, engine runs, chunks go out (docs/spec.md §3-§4).

One thread owns the device. Whenever the device is free and some robot has a useful request, it
plans a batch through the dispatch step (:class:`~lerobot_armory.dispatch.Dispatcher`, under the
fleet lock, a fraction of a millisecond), takes each chosen robot's *latest* observation,
releases the lock, runs one batched forward pass, completes the plan and hands each robot its
chunk (tagged with ``i_start``, the index of the observation it was computed from). Network threads keep feeding observations while the
model runs; they never wait for it and it never waits for them.
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lerobot_armory.arbiter import PolicyArbiter
from lerobot_armory.dispatch import Dispatcher, Plan
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.transition import Chunk
from lerobot_armory.inference_latency import LatencyProfile, OnlineLatency
from lerobot_armory.schedulers.base import Scheduler
from lerobot_armory.engine.faults import Fault, classify
from lerobot_armory.engine.protocol import Engine, noise_seed
from lerobot_armory.serving.fleet import Fleet
from lerobot_armory.serving.session import DEFAULT_POLICY, RobotSession
from lerobot_armory.serving.messages import ChunkOut, Notice, NoticeKind
from lerobot_armory.engine.rtc import Prefix

log = logging.getLogger(__name__)

# Warn (once per excursion) when the learnt d_infer moves this far from the start-up profile.
DRIFT_WARN_PCT = 25.0
# This many failed batches in a row, across whichever robots they held, mean the engine is broken,
# not one request: the loop stops and the server exits 1 (a supervisor restarts it) rather than
# failing every robot's every request forever. Errors known to leave the device unusable stop it
# at the first (engine/faults.py); out-of-memory lowers the batch cap instead of failing.
MAX_CONSECUTIVE_FAILURES = 20
# With RTC, sent chunks kept per robot for the next leftovers (the mirror's queue holds fewer).
MAX_MODEL_CHUNKS = 16


@dataclass
class ServedPolicy:
    """One policy the loop serves: its engine, its scheduler (its own ``d_infer(b)`` and batch
    cap), the dispatcher over its robots and, optionally, the latency model its batches feed."""

    name: str
    engine: Engine
    scheduler: Scheduler
    latency: OnlineLatency | None = None
    dispatcher: Dispatcher = field(init=False)
    drift_warned: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        if self.latency is not None and self.latency.max_batch_size != self.scheduler.max_batch_size:
            raise ValueError(
                f"latency model covers b <= {self.latency.max_batch_size}, the scheduler b <= {self.scheduler.max_batch_size}"
            )
        self.dispatcher = Dispatcher(self.scheduler, isolate_failures=True)

    @property
    def rtc(self) -> bool:
        """Real-time chunking: the engine guides each chunk by the prefix the mirror predicts."""
        return self.engine.rtc is not None

    @property
    def max_batch_size(self) -> int:
        """This policy's batch cap: the one value the scheduler plans with, the loop reports and
        the next swap warms up and profiles for (the scheduler holds it; read it here)."""
        return self.scheduler.max_batch_size

    def lower_cap(self, cap: int) -> None:
        """Lower the batch cap to ``cap`` (a batch of more ran out of device memory): the next
        plan, the latency model's table and the next swap's warm-up all stop at ``cap``."""
        cap = max(1, min(cap, self.max_batch_size))
        self.scheduler.max_batch_size = cap
        if self.latency is not None:
            self.latency.lower_cap(cap)


@dataclass
class Batch:
    """A dispatched plan joined to the live data of its robots (aligned with ``plan.requests``)."""

    plan: Plan
    policy: ServedPolicy
    sessions: list[RobotSession]
    observations: list[dict[str, np.ndarray]]
    prefixes: list[Prefix | None] | None = None  # with RTC: what each robot executes meanwhile
    history: list[list[dict[str, np.ndarray]]] | None = None  # with history_steps > 1: each robot's last observations


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
    rtc_delays: list[int | None] | None = None  # with RTC: each robot's predicted inference delay
    chunk_ids: list[int] | None = None  # each robot's chunk id (what its ActionChunk carries)
    policy: str = DEFAULT_POLICY  # the policy that ran the batch


@dataclass
class LoopStats:
    """Running counters of the serving loop."""

    batches: int = 0
    failed_batches: int = 0
    batch_sizes: collections.Counter = field(default_factory=collections.Counter)
    batches_by_policy: collections.Counter = field(default_factory=collections.Counter)
    infer_ms: dict[int, collections.deque] = field(default_factory=lambda: collections.defaultdict(lambda: collections.deque(maxlen=200)))
    decision_ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=1000))
    # CPU time of the same decisions: the scheduler's own cost, without waits for the GIL or
    # for a core (on a loaded 2-core machine wall time mostly measures those).
    decision_cpu_ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=1000))
    failed_decisions: int = 0  # decisions the scheduler could not make (served in order instead)
    oom_batches: int = 0  # batches that ran out of device memory and lowered the cap (not failed)
    unrecorded_batches: int = 0  # batches served without the CUDA graph meant for them (eager speed)
    batch_cap: int | None = None  # the cap after an out-of-memory batch lowered it (None: as configured)
    busy_s: float = 0.0
    idle_with_work_s: float = 0.0
    started: float = 0.0


class ServingLoop:
    """Runs the scheduler/engine loop on its own thread until :meth:`stop`.

    Args:
        fleet: the shared fleet state.
        engine: an :class:`~lerobot_armory.engine.protocol.Engine`.
        scheduler: a registered scheduler built for the engine's latency profile.
        on_batch: optional callback with each :class:`BatchRecord` (batch logs).
        latency: if given, every served batch's time feeds this model and its table replaces the
            scheduler's ``d_infer`` whenever it changes (None: the table stays as built).
        policy_name: the name of the policy ``engine`` serves (sessions name it).
        others: more policies served from the same device. Each batch holds robots of one
            policy; a :class:`~lerobot_armory.arbiter.PolicyArbiter` picks whose batch runs next.
    """

    def __init__(
        self,
        fleet: Fleet,
        engine: Engine,
        scheduler: Scheduler,
        on_batch: Callable[[BatchRecord], None] | None = None,
        latency: OnlineLatency | None = None,
        policy_name: str = DEFAULT_POLICY,
        others: tuple[ServedPolicy, ...] = (),
    ) -> None:
        self.fleet = fleet
        first = ServedPolicy(policy_name, engine, scheduler, latency)
        self.policies: dict[str, ServedPolicy] = {first.name: first}
        for other in others:
            if other.name in self.policies:
                raise ValueError(f"two policies named {other.name!r}")
            self.policies[other.name] = other
        self.default_policy = first.name
        self.arbiter = PolicyArbiter({name: p.dispatcher for name, p in self.policies.items()})
        self.on_batch = on_batch
        self._failures_in_a_row = 0
        self.stats = LoopStats(started=fleet.clock())
        self._thread = threading.Thread(target=self._run, name="armory-serving-loop", daemon=True)
        self._last_end: float | None = None
        self._work_at_last_end = False
        self.error: BaseException | None = None
        # A policy swap (serving/swap.py): the engine and d_infer table to switch to at the next
        # batch boundary, whether dispatching is held (a drain), and whether a batch is in flight.
        self._pending: tuple[str, Engine, list[float] | None] | None = None
        self._held = False
        self._busy = False
        self.switched_at_batch: int | None = None  # loop batches served before the last switch

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float | None = None) -> None:
        """Stop after the in-flight batch (its chunks are still delivered)."""
        self.fleet.stop()
        self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    # The first policy's parts: a server of one policy has only these.
    @property
    def engine(self) -> Engine:
        return self.policies[self.default_policy].engine

    @property
    def scheduler(self) -> Scheduler:
        return self.policies[self.default_policy].scheduler

    @property
    def dispatcher(self) -> Dispatcher:
        return self.policies[self.default_policy].dispatcher

    @property
    def latency(self) -> OnlineLatency | None:
        return self.policies[self.default_policy].latency

    # ---- policy swaps (serving/swap.py) ------------------------------------------------------

    def hold(self, timeout: float) -> bool:
        """Stop dispatching and wait until no batch is in flight (its chunks are queued by then).

        Robots keep streaming and see a delay, not an error. False: the in-flight batch did not
        finish in ``timeout`` or the loop stopped (the hold stays on; :meth:`resume` lifts it)."""
        with self.fleet.cond:
            self._held = True
            self.fleet.cond.notify_all()
            return self.fleet.cond.wait_for(lambda: not self._busy or self.fleet.stopping, timeout) and not self.fleet.stopping

    def resume(self) -> None:
        """Dispatch again after :meth:`hold`."""
        with self.fleet.cond:
            self._held = False
            self.fleet.cond.notify_all()

    def switch(self, engine: Engine, d_infer: list[float] | None, timeout: float, policy: str | None = None) -> int | None:
        """Serve every batch from the next one on with ``engine`` (and ``d_infer`` as the scheduler's
        table, None: unchanged); returns the loop's batch count at the switch once it happened.

        The switch happens on the loop's own thread between two batches, under the fleet lock:
        the batch in flight finishes on the old engine and its chunks are queued before it, and
        no batch after it runs on the old engine. None: the loop stopped or did not reach a batch
        boundary within ``timeout`` (the switch is withdrawn). ``policy``: which policy's engine
        (None: the first)."""
        with self.fleet.cond:
            self._pending = (policy or self.default_policy, engine, d_infer)
            self.fleet.cond.notify_all()
            done = self.fleet.cond.wait_for(lambda: self._pending is None or self.fleet.stopping, timeout)
            if not done or self._pending is not None:
                self._pending = None
                return None
            return self.switched_at_batch

    def cap_of(self, policy: str | None = None) -> int:
        """The batch cap of ``policy`` now (None: the first policy's)."""
        with self.fleet.cond:
            return self.policies[policy or self.default_policy].max_batch_size

    def _apply_switch(self) -> None:
        """Take the pending engine (fleet lock held, loop thread, no batch in flight)."""
        assert self._pending is not None
        name, engine, table = self._pending
        served = self.policies[name]
        served.engine = engine
        if table is not None:
            served.scheduler.d_infer[:] = table
            if served.latency is not None:
                served.latency.restart(LatencyProfile("swapped", tuple(1000.0 * t for t in table), source="profiled"))
        self._failures_in_a_row = 0
        self._last_end = None  # the pause of a drain is not idle time with work waiting
        self.switched_at_batch = self.stats.batches
        self._pending = None
        self.fleet.cond.notify_all()

    def _run(self) -> None:
        try:
            while True:
                batch = self._next_batch()
                if batch is None:
                    return
                if batch.plan.requests:
                    self._serve(batch)
        except BaseException as exc:  # pragma: no cover - a bug; logged and surfaced by the server
            self.error = exc
            log.exception("serving loop crashed")
            raise

    def _next_batch(self) -> Batch | None:
        """Wait until some robot has a useful request, then plan the batch (fleet lock held)."""
        fleet = self.fleet
        with fleet.cond:
            while True:
                while True:
                    if self._pending is not None:
                        self._apply_switch()
                    if fleet.stopping:
                        return None
                    if self._held:
                        fleet.cond.wait(0.25)
                        continue
                    now = fleet.clock()
                    # A robot over its granted share of device time waits until the share decays;
                    # a robot without a stored observation has nothing to serve.
                    active = fleet.active()
                    sessions = [s for s in active if s.latest is not None and not fleet.over_share(s, now)]
                    mirrors = self._mirrors_by_policy(sessions)
                    if self.arbiter.has_work(mirrors):
                        break
                    fleet.cond.wait(0.05 if len(sessions) < len(active) else 0.25)
                planned = self.arbiter.plan(mirrors, now)
                assert planned is not None  # has_work held under the same lock
                name, plan = planned
                if plan.wait_until is None:
                    break
                # Dispatch timing: an observation about to land makes the batch better. Every
                # observation notifies the condition, so the loop plans again as soon as one
                # lands, or when the wait ends (the dispatcher caps it at the scheduler's max).
                self.stats.decision_ms.append(plan.decision_s * 1000.0)
                self.stats.decision_cpu_ms.append(plan.decision_cpu_s * 1000.0)
                fleet.cond.wait(max(0.0, plan.wait_until - now))
            if self._last_end is not None and self._work_at_last_end:
                self.stats.idle_with_work_s += max(0.0, now - self._last_end)
            by_id = {s.robot_id: s for s in sessions}
            for robot_id, why in plan.quarantined:
                log.error("dropping robot %s: its state cannot be scheduled (%s)", robot_id, why)
                fleet.quarantine(by_id[robot_id], f"your session was ended: the server cannot schedule your state ({why})")
            self.stats.decision_ms.append(plan.decision_s * 1000.0)
            self.stats.decision_cpu_ms.append(plan.decision_cpu_s * 1000.0)
            self.stats.failed_decisions += plan.fell_back
            chosen = [by_id[r.robot_id] for r in plan.requests]
            fleet.in_flight = {s.session_id for s in chosen}
            served = self.policies[name]
            prefixes = [_prefix(s, r.mirror, r.chunk) for s, r in zip(chosen, plan.requests, strict=True)] if served.rtc else None
            steps = served.engine.history_steps
            history = [s.history(steps) for s in chosen] if steps > 1 else None
            self._busy = bool(chosen)
            return Batch(plan, served, chosen, [s.latest for s in chosen], prefixes, history)

    def _mirrors_by_policy(self, sessions: list[RobotSession]) -> dict[str, list[RobotMirror]]:
        """The sessions' mirrors grouped by the policy each robot registered for (registration order)."""
        out: dict[str, list[RobotMirror]] = {}
        for s in sessions:
            out.setdefault(s.policy if s.policy in self.policies else self.default_policy, []).append(s.mirror)
        return out

    def _serve(self, batch: Batch) -> None:
        fleet = self.fleet
        plan = batch.plan
        engine = batch.policy.engine
        t_start = fleet.clock()
        unrecorded: int | None = None  # the engine's count of batches without their CUDA graph, before this one
        try:
            tasks = [s.task for s in batch.sessions]
            model_actions = None
            seeds = [noise_seed(r.robot_id, r.chunk.chunk_id) for r in plan.requests]
            unrecorded = engine.unrecorded_batches
            if batch.prefixes is not None:
                actions, model_actions = engine.infer_guided(batch.observations, tasks, seeds, batch.prefixes)
            else:
                actions = engine.infer(batch.observations, tasks, seeds, batch.history)
            if actions.shape[0] != plan.size:
                raise RuntimeError(f"engine returned {actions.shape[0]} chunks for a batch of {plan.size}")
        except Exception as exc:
            self._count_unrecorded(engine, unrecorded)
            self._fail(batch, exc, t_start)
            return
        t_done = fleet.clock()
        self._failures_in_a_row = 0
        self._count_unrecorded(engine, unrecorded)
        with fleet.cond:
            batch.policy.dispatcher.complete(plan, t_done)
            for k, (request, session) in enumerate(zip(plan.requests, batch.sessions, strict=True)):
                if fleet.sessions.get(session.session_id) is not session:
                    continue  # the robot left while its batch ran: its chunk goes nowhere
                chunk = request.chunk
                if model_actions is not None:
                    _keep_model_chunk(session, chunk.chunk_id, model_actions[k])
                msg = ChunkOut(
                    chunk.chunk_id, chunk.i_start, np.ascontiguousarray(actions[k], dtype=np.float32), t_done, chunk.capture_robot,
                    chunk.episode,
                )
                fleet.record_sent(session, t_done)
                session.outbox.put(msg)
                if session.move_after_chunk:
                    fleet.move_now(session)
            fleet.in_flight = set()
            self._busy = False
            fleet.charge_device(batch.sessions, t_done - t_start, t_done)
            self._finish(batch.policy.name, plan.size, t_start, t_done)
            fleet.cond.notify_all()
        if batch.policy.latency is not None:
            self._learn(batch.policy, plan.size, t_done - t_start)
        self._record(batch.policy.name, plan, t_start, t_done, ok=True, prefixes=batch.prefixes)

    def _count_unrecorded(self, engine: Engine, before: int | None) -> None:
        """Count the batch if the engine served it without its CUDA graph (its running count grew
        since ``before``; None: the count could not be read, nothing to compare)."""
        try:
            if before is not None and engine.unrecorded_batches > before:
                self.stats.unrecorded_batches += 1
        except Exception:  # a broken engine fails its batch on its own: the count is an extra
            pass

    def _learn(self, served: ServedPolicy, size: int, seconds: float) -> None:
        """Feed one served batch to the latency model; hand a changed table to the scheduler.

        Failed batches are not fed: an exception's timing says nothing about inference.
        """
        model = served.latency
        assert model is not None
        if not model.observe(size, seconds):
            return  # the published table did not move: the scheduler keeps its list untouched
        table = model.table_s()
        with self.fleet.cond:
            # In place, under the lock every decision holds: schedulers read self.d_infer on each
            # decision (some keep a local alias for its duration), and none sees a half-written table.
            served.scheduler.d_infer[:] = table
        worst = model.max_drift()
        if abs(worst.pct) > DRIFT_WARN_PCT and not served.drift_warned:
            served.drift_warned = True
            log.warning(
                "%s: d_infer drifted %+.0f%% from the start-up profile at b=%d (%.1f -> %.1f ms); the scheduler now uses "
                "the measured table: %s ms",
                served.name, worst.pct, worst.batch_size, worst.startup_ms, worst.current_ms,
                ", ".join(f"{ms:.1f}" for ms in model.table_ms()),
            )  # fmt: skip
        elif abs(worst.pct) < DRIFT_WARN_PCT / 2:
            served.drift_warned = False  # back near the profile: warn again on the next excursion

    def _fail(self, batch: Batch, exc: Exception, t_start: float) -> None:
        """An engine error hurts only this batch (:mod:`lerobot_armory.engine.faults`).

        A batch that ran out of device memory lowers the batch cap below its size, and its robots
        are served again in smaller batches without being told of an error (they see a delay). A
        lost device stops the loop at once (the server exits 1, a supervisor restarts it). Any
        other error fails this batch: its robots are told and become useful again.
        """
        plan = batch.plan
        fault = classify(exc)
        shrink = fault is Fault.OUT_OF_MEMORY and plan.size > 1
        if shrink:
            log.warning(
                "out of device memory at a batch of %d (%s): the batch cap is now %d until restart; these robots are "
                "served again in smaller batches", plan.size, _first_line(exc), plan.size - 1,
            )  # fmt: skip
        else:
            log.error("inference failed for a batch of %d (%s): %s", plan.size, ", ".join(plan.robot_ids), exc)
        t_end = self.fleet.clock()
        served = batch.policy
        with self.fleet.cond:
            served.dispatcher.cancel(plan)
            self.fleet.in_flight = set()
            self._busy = False
            if shrink:
                served.lower_cap(plan.size - 1)
                self.stats.batch_cap = served.max_batch_size
                self.stats.oom_batches += 1
            else:
                self.stats.failed_batches += 1
            for request, session in zip(plan.requests, batch.sessions, strict=True):
                if not shrink:
                    session.outbox.put(
                        Notice(
                            NoticeKind.INFERENCE_FAILED,
                            f"inference failed for this batch ({type(exc).__name__}: {exc}); your next observation will be served",
                            request.chunk.i_start,
                        )
                    )
                if session.move_after_chunk and self.fleet.sessions.get(session.session_id) is session:
                    self.fleet.move_now(session)  # no chunk is coming: the move need not wait
            self._finish(served.name, plan.size, t_start, t_end)
            self.fleet.cond.notify_all()
        self._record(served.name, plan, t_start, t_end, ok=False)
        if shrink:
            return
        self._failures_in_a_row += 1
        if fault is Fault.DEVICE_LOST:
            self.error = RuntimeError(f"the device is lost ({type(exc).__name__}: {_first_line(exc)}); restart the server")
        elif self._failures_in_a_row >= MAX_CONSECUTIVE_FAILURES:
            # An error this module does not know as sticky may still fail every batch.
            self.error = RuntimeError(
                f"the engine is broken ({self._failures_in_a_row} failed batches in a row; last: {type(exc).__name__}: {exc})"
            )
        if self.error is not None:
            log.error("stopping: %s", self.error)
            self.fleet.stop()  # the loop ends at its next decision; the server sees loop.error and exits 1

    def _finish(self, policy: str, size: int, t_start: float, t_end: float) -> None:
        """Counters at the end of a batch (lock held)."""
        self.stats.batches += 1
        self.stats.batch_sizes[size] += 1
        self.stats.batches_by_policy[policy] += 1
        self.stats.infer_ms[size].append((t_end - t_start) * 1000.0)
        self.stats.busy_s += t_end - t_start
        self._last_end = t_end
        self._work_at_last_end = any(s.mirror.is_useful() for s in self.fleet.active())

    def _record(
        self, policy: str, plan: Plan, t_start: float, t_end: float, ok: bool, prefixes: list[Prefix | None] | None = None
    ) -> None:
        if self.on_batch is not None:
            chunks = [r.chunk for r in plan.requests]
            self.on_batch(
                BatchRecord(
                    t_start,
                    t_end,
                    plan.robot_ids,
                    [c.i_start for c in chunks],
                    [c.obs_recv for c in chunks],
                    plan.decision_s * 1000.0,
                    ok,
                    None if prefixes is None else [None if p is None else p.inference_delay for p in prefixes],
                    [c.chunk_id for c in chunks],
                    policy,
                )
            )


def _prefix(session: RobotSession, mirror: RobotMirror, chunk: Chunk) -> Prefix | None:
    """The RTC prefix of one request: the mirror's predicted delay and the actions it says the
    robot executes meanwhile, cut from the chunks sent to it (None: nothing to continue from).

    The last piece runs on to the end of its chunk, past ``h_max`` where the robot itself would
    stop: those actions are the policy's own continuation of the motion, and the new chunk,
    which a robot with ``h_max < H`` switches to right there, should continue it too.
    """
    try:
        predicted = mirror.prefix_of(chunk)
    except Exception as exc:  # a state the prediction cannot read: this robot's chunk goes unguided, the batch goes on
        log.warning("no RTC prefix for robot %s: %s", mirror.spec.robot_id, exc)
        return None
    if predicted is None:
        return None
    pieces = []
    last = len(predicted.segments) - 1
    for k, (chunk_id, offset, count) in enumerate(predicted.segments):
        sent = session.model_chunks.get(chunk_id)
        if sent is None or offset >= len(sent):
            break  # not a chunk of this session's (sent before a reconnect): continue from what is known
        pieces.append(sent[offset:] if k == last else sent[offset : offset + count])
    if not pieces:
        return None
    return Prefix(np.concatenate(pieces), predicted.inference_delay)  # cut to the chunk size by the engine


def _keep_model_chunk(session: RobotSession, chunk_id: int, actions: np.ndarray) -> None:
    """Keep a sent chunk for the next leftovers; drop those the mirror no longer holds."""
    session.model_chunks[chunk_id] = actions
    live = {c.chunk_id for c in session.mirror.queue}
    if session.mirror.ran_out is not None:
        live.add(session.mirror.ran_out.chunk_id)
    for old in [cid for cid in session.model_chunks if cid not in live and cid != chunk_id]:
        del session.model_chunks[old]
    while len(session.model_chunks) > MAX_MODEL_CHUNKS:  # oldest first (insertion order)
        del session.model_chunks[next(iter(session.model_chunks))]


def _first_line(exc: BaseException) -> str:
    return (str(exc).strip().splitlines() or [""])[0][:200]
