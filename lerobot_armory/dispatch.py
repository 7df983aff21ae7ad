"""The dispatch step: the one place where a scheduler's choice becomes requests on the mirrors.

vLLM v1 splits its engine step into ``schedule()`` (decide, book the requests) and
``update_from_output()`` (book the results). A fleet has the same two moments, and every driver
of the mirrors (the live loop in ``serving/loop.py`` on wall time, the simulator in
``sim/simulator.py`` on simulated time, the offline study in ``research/``) goes through them:

- :meth:`Dispatcher.plan` at ``now``: the scheduler picks the batch among the mirrors,
  :func:`~lerobot_armory.schedulers.base.check_batch` checks its contract, and each chosen
  mirror books its chunk (``i_start`` = its latest observation's index, arrival predicted from
  ``now + d_infer(b)``). The plan names each request by robot id: a driver joins it to its own
  data (a session, a ground-truth robot) with a dict, never by object identity or position.
- :meth:`Dispatcher.complete` at ``t_done``: the batch finished and its chunks were sent; the
  mirrors replace the predicted completion with the real one.
- :meth:`Dispatcher.cancel`: the batch failed; its robots are useful again and the prediction
  no longer counts on their chunks.

A plan may also say *wait* (:attr:`Plan.wait_until`, nothing booked): the scheduler's dispatch
timing (:mod:`lerobot_armory.schedulers.dispatch_timing`) predicts that an observation about to land makes
the batch better at no cost. The driver then plans again at ``wait_until`` or as soon as any
observation lands, whichever is first; the dispatcher caps the total wait of one free device at
the scheduler's ``max_wait_s``, so a wait can never become a stall.

The dispatcher holds no clock and does no I/O, like the mirror and the schedulers.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

from lerobot_armory.mirror import RobotMirror
from lerobot_armory.transition import Chunk
from lerobot_armory.schedulers.base import Scheduler, check_batch

log = logging.getLogger(__name__)


@dataclass(slots=True)
class Request:
    """One robot's request inside a plan.

    Attributes:
        robot_id: the robot (``mirror.spec.robot_id``): the key a driver joins on.
        mirror: its mirror.
        chunk: the chunk booked in the mirror's queue (``i_start``, predicted ``t_arrival``;
            the observation's stamps ``capture_robot`` / ``obs_recv``).
        previous_last_served: the mirror's last served index before this request (restored by
            :meth:`Dispatcher.cancel`).
    """

    robot_id: str
    mirror: RobotMirror
    chunk: Chunk
    previous_last_served: int | None


@dataclass
class Plan:
    """One dispatched batch, from decision to completion.

    Attributes:
        now: decision time.
        requests: the batch, in the scheduler's order.
        t_done: predicted completion (``now + d_infer(b)``), then the real one once completed.
        decision_s / decision_cpu_s: the decision's wall and CPU (thread) time, seconds.
        quarantined: ``(robot_id, why)`` of robots left out because their mirror cannot be
            evaluated (only with ``isolate_failures``): the driver ends their sessions.
        fell_back: the scheduler failed even without them, so the first useful robots were taken.
        wait_until: set (and ``requests`` empty) when the device should wait: plan again at this
            time or when an observation lands, whichever is first.
    """

    now: float
    requests: list[Request]
    t_done: float
    decision_s: float = 0.0
    decision_cpu_s: float = 0.0
    quarantined: list[tuple[str, str]] = field(default_factory=list)
    fell_back: bool = False
    wait_until: float | None = None

    @property
    def size(self) -> int:
        return len(self.requests)

    @property
    def robot_ids(self) -> list[str]:
        return [r.robot_id for r in self.requests]


@dataclass
class Proposal:
    """A scheduler's decision before it is booked (:meth:`Dispatcher.propose`).

    Attributes:
        now: decision time.
        chosen: the batch's mirrors, in the scheduler's order (empty: all quarantined).
        decision_s / decision_cpu_s: the decision's wall and CPU time so far, seconds.
        quarantined / fell_back: as :class:`Plan`'s.
        score: the scheduler's own score of the batch (``last_score``; None if it keeps none):
            what an arbiter between policies compares when their schedulers score batches.
    """

    now: float
    chosen: list[RobotMirror]
    decision_s: float
    decision_cpu_s: float
    quarantined: list[tuple[str, str]] = field(default_factory=list)
    fell_back: bool = False
    score: float | None = None

    @property
    def deadline(self) -> float:
        """The soonest deadline among the chosen robots (inf: none)."""
        return min((m.deadline() for m in self.chosen), default=float("inf"))


class Dispatcher:
    """Owns the dispatch step for one scheduler (see the module docstring).

    Args:
        scheduler: any registered scheduler.
        isolate_failures: live serving sets it: a scheduler that raises does not stop the
            fleet. The robots whose mirror cannot be evaluated (as schedulers evaluate it) are
            left out and reported in :attr:`Plan.quarantined`; if the scheduler still fails, the
            first useful robots are served in order (:attr:`Plan.fell_back`). Off (simulator,
            study): the exception propagates, since it is a bug to see, not traffic to survive.
    """

    def __init__(self, scheduler: Scheduler, isolate_failures: bool = False) -> None:
        self.scheduler = scheduler
        self.isolate_failures = isolate_failures
        self._held_since: float | None = None  # the device has been waiting (dispatch timing) since
        self.held_s = 0.0  # total time the device waited on purpose (dispatch timing)
        self.holds = 0  # plans that said wait

    @staticmethod
    def has_work(mirrors: Sequence[RobotMirror]) -> bool:
        """Whether some robot has a useful request (docs/spec.md §3): the device should not idle."""
        return any(m.is_useful() for m in mirrors)

    def plan(self, mirrors: Sequence[RobotMirror], now: float) -> Plan | None:
        """Decide the next batch among ``mirrors`` (registration order) at ``now`` and book it.

        Returns None when no robot has a useful request.
        """
        proposal = self.propose(mirrors, now)
        if proposal is None:
            return None
        return self.book(proposal, mirrors)

    def propose(self, mirrors: Sequence[RobotMirror], now: float) -> Proposal | None:
        """The scheduler's batch among ``mirrors`` at ``now``, booked nowhere yet (None: no robot
        has a useful request). Several policies' dispatchers propose and one proposal is booked
        (:mod:`lerobot_armory.arbiter`); a proposal must be booked before the mirrors change."""
        if not self.has_work(mirrors):
            self._stop_holding(now)
            return None
        t0, c0 = time.perf_counter(), time.thread_time()
        chosen, quarantined, fell_back = self._choose(mirrors, now)
        score = getattr(self.scheduler, "last_score", None)
        return Proposal(now, chosen, time.perf_counter() - t0, time.thread_time() - c0, quarantined, fell_back, score)

    def book(self, proposal: Proposal, mirrors: Sequence[RobotMirror]) -> Plan:
        """Book ``proposal`` on its mirrors, or say wait (:attr:`Plan.wait_until`) if the
        scheduler's dispatch timing holds the device for an observation about to land."""
        now, chosen = proposal.now, proposal.chosen
        t0, c0 = time.perf_counter(), time.thread_time()
        hold = self._hold(mirrors, chosen, now) if chosen and not proposal.fell_back and not proposal.quarantined else None
        decision_s = proposal.decision_s + time.perf_counter() - t0
        decision_cpu_s = proposal.decision_cpu_s + time.thread_time() - c0
        if hold is not None:
            self.holds += 1
            return Plan(now, [], now, decision_s, decision_cpu_s, wait_until=hold)
        self._stop_holding(now)
        if not chosen:  # every useful robot was quarantined
            return Plan(now, [], now, decision_s, decision_cpu_s, proposal.quarantined, proposal.fell_back)
        t_done = now + self.scheduler.d_infer[len(chosen) - 1]
        requests = []
        for mirror in chosen:
            previous = mirror.last_served_index
            requests.append(Request(mirror.spec.robot_id, mirror, mirror.on_dispatch(t_done), previous))
        return Plan(now, requests, t_done, decision_s, decision_cpu_s, proposal.quarantined, proposal.fell_back)

    def complete(self, plan: Plan, t_done: float) -> None:
        """The plan's batch finished at ``t_done`` and its chunks go out now."""
        plan.t_done = t_done
        for request in plan.requests:
            request.mirror.on_complete(request.chunk, t_done)

    def cancel(self, plan: Plan) -> None:
        """The plan's batch will never be delivered."""
        for request in plan.requests:
            request.mirror.on_cancel(request.chunk, request.previous_last_served)

    # ---- the decision -------------------------------------------------------------------------

    def _stop_holding(self, now: float) -> None:
        if self._held_since is not None:
            self.held_s += max(0.0, now - self._held_since)
            self._held_since = None

    def _hold(self, mirrors: Sequence[RobotMirror], batch: list[RobotMirror], now: float) -> float | None:
        """The scheduler's wait, if any, capped so the device waits at most ``max_wait_s`` in
        all since it was first told to wait (None: dispatch now)."""
        scheduler = self.scheduler
        if scheduler.max_wait_s <= 0:
            return None
        start = now if self._held_since is None else self._held_since
        limit = start + scheduler.max_wait_s
        if now >= limit:
            return None
        try:
            until = scheduler.hold(mirrors, batch, now)
        except Exception:
            if not self.isolate_failures:
                raise
            log.exception("%s failed to time its batch; dispatching now", type(scheduler).__name__)
            return None
        if until is None or not until > now:
            return None
        self._held_since = start
        return min(until, limit)

    def _choose(self, mirrors: Sequence[RobotMirror], now: float) -> tuple[list[RobotMirror], list[tuple[str, str]], bool]:
        scheduler = self.scheduler
        name = type(scheduler).__name__
        if not self.isolate_failures:
            batch = scheduler.select(mirrors, now)
            check_batch(batch, scheduler.max_batch_size, name)
            return batch, [], False
        quarantined: list[tuple[str, str]] = []
        pool = list(mirrors)
        for attempt in range(2):
            try:
                batch = scheduler.select(pool, now)
                check_batch(batch, scheduler.max_batch_size, name)
                return batch, quarantined, False
            except Exception as exc:  # noqa: BLE001 - isolated below: the fleet must go on
                error = exc
                if attempt == 0:
                    pool, quarantined = _evaluable(pool, now)
        log.error("%s failed to decide (%s: %s); serving the first useful robots in order", name, type(error).__name__, error)
        return [m for m in pool if m.is_useful()][: scheduler.max_batch_size], quarantined, True


def _evaluable(mirrors: Sequence[RobotMirror], now: float) -> tuple[list[RobotMirror], list[tuple[str, str]]]:
    """Split ``mirrors`` into those every scheduler can evaluate (their deadline, predicted index
    and window rollout compute) and ``(robot_id, why)`` for the others."""
    kept, broken = [], []
    for mirror in mirrors:
        try:
            mirror.deadline()
            mirror.predicted_index(now)
            mirror.window_view(now, 1.0).executed()
        except Exception as exc:  # noqa: BLE001 - this robot's state is broken, not the fleet
            broken.append((mirror.spec.robot_id, f"{type(exc).__name__}: {exc}"))
            continue
        kept.append(mirror)
    return kept, broken
