"""The server's fleet state: one session per registered robot, each with its mirror.

Every mutation happens under one condition variable (``Fleet.cond``), shared by the network
threads (which feed observations and reports) and the serving loop (which reads the mirrors,
dispatches batches and delivers chunks). Holding it is always short: decoding happens before, and
inference after, the lock.
"""

from __future__ import annotations

import collections
import math
import threading
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lerobot_armory.mirror import Chunk, RobotMirror, RobotSpec
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.wire import FeatureSpec


class FleetError(Exception):
    """A request the fleet refuses; ``code`` names the gRPC status to answer with."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class Outbox:
    """Messages waiting to be written to one robot's stream.

    Never blocks the producer (the serving loop): if the robot stops reading, older *chunks* are
    dropped once ``limit`` messages wait — a newer chunk supersedes them anyway — while notices
    are kept. ``get`` returns None once closed and drained.
    """

    def __init__(self, limit: int = 8) -> None:
        self._items: collections.deque[pb.ServerMessage] = collections.deque()
        self._cond = threading.Condition()
        self._closed = False
        self.limit = limit
        self.dropped_chunks = 0

    def put(self, msg: pb.ServerMessage) -> None:
        with self._cond:
            if self._closed:
                return
            self._items.append(msg)
            while len(self._items) > self.limit:
                for k, old in enumerate(self._items):
                    if old.WhichOneof("kind") == "chunk":
                        del self._items[k]
                        self.dropped_chunks += 1
                        break
                else:
                    break
            self._cond.notify()

    def get(self, timeout: float | None = None) -> pb.ServerMessage | None:
        with self._cond:
            while not self._items and not self._closed:
                if not self._cond.wait(timeout):
                    return None
            return self._items.popleft() if self._items else None

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed


@dataclass
class ChunkRecord:
    """What the server remembers of a sent chunk until the robot reports its arrival."""

    capture_robot: float
    obs_recv: float
    send_time: float


@dataclass
class RobotSession:
    """A registered robot: its spec, mirror, latest observation and stream."""

    session_id: str
    spec: RobotSpec
    task: str
    features: dict[str, FeatureSpec]
    mirror: RobotMirror
    registered_at: float
    outbox: Outbox = field(default_factory=Outbox)
    streaming: bool = False
    latest: dict[str, np.ndarray] | None = None
    sent: dict[int, ChunkRecord] = field(default_factory=dict)
    # counters (reported by the robot, or counted here)
    observations: int = 0
    rejected: int = 0
    chunks_sent: int = 0
    reported_executed: int = 0
    reported_starved: int = 0
    reported_index: int | None = None
    index_error: int | None = None  # |mirror's predicted index - robot's reported index| at last report
    last_chunk_time: float | None = None
    rate: Any = None  # the session's observation RateLimiter, if limits are on
    rate_notified: float = 0.0
    first_executed: collections.Counter = field(default_factory=collections.Counter)

    @property
    def robot_id(self) -> str:
        return self.spec.robot_id

    @property
    def reported_starvation_pct(self) -> float:
        total = self.reported_executed + self.reported_starved
        return 100.0 * self.reported_starved / total if total else 0.0


class Fleet:
    """All sessions, in registration order, behind one condition variable."""

    def __init__(self, clock: Callable[[], float], max_robots: int = 64, stale_session_s: float = 30.0) -> None:
        self.clock = clock
        self.max_robots = max_robots
        self.stale_session_s = stale_session_s
        self.cond = threading.Condition()
        self.sessions: dict[str, RobotSession] = {}
        self.stopping = False

    # ---- membership --------------------------------------------------------------------------

    def register(self, spec: RobotSpec, task: str, features: dict[str, FeatureSpec]) -> RobotSession:
        """Add a robot. A robot id already *streaming* is refused; a stale registration of the
        same id (never streamed, or its stream ended) is replaced."""
        with self.cond:
            if self.stopping:
                raise FleetError("UNAVAILABLE", "the server is shutting down")
            for sid, s in list(self.sessions.items()):
                if s.robot_id == spec.robot_id:
                    if s.streaming:
                        raise FleetError("ALREADY_EXISTS", f"robot id {spec.robot_id!r} is already connected")
                    self._drop(sid)
            self._expire_unstreamed()
            if len(self.sessions) >= self.max_robots:
                raise FleetError("RESOURCE_EXHAUSTED", f"the server already serves {self.max_robots} robots (--max_robots)")
            session = RobotSession(uuid.uuid4().hex, spec, task, features, RobotMirror(spec), self.clock())
            self.sessions[session.session_id] = session
            return session

    def attach(self, session_id: str) -> RobotSession:
        """Mark a session's stream open (one stream per session)."""
        with self.cond:
            session = self.sessions.get(session_id)
            if session is None:
                raise FleetError("FAILED_PRECONDITION", "unknown or expired session: call Register first")
            if session.streaming:
                raise FleetError("ALREADY_EXISTS", f"robot {session.robot_id!r} already has an open stream")
            session.streaming = True
            return session

    def detach(self, session_id: str) -> None:
        """The stream ended: forget the robot (a reconnecting robot registers again)."""
        with self.cond:
            self._drop(session_id)
            self.cond.notify_all()

    def _drop(self, session_id: str) -> None:
        session = self.sessions.pop(session_id, None)
        if session is not None:
            session.outbox.close()

    def _expire_unstreamed(self) -> None:
        now = self.clock()
        for sid, s in list(self.sessions.items()):
            if not s.streaming and now - s.registered_at > self.stale_session_s:
                self._drop(sid)

    def active(self) -> list[RobotSession]:
        """Sessions with an open stream, in registration order (call with the lock held)."""
        return [s for s in self.sessions.values() if s.streaming]

    # ---- events from the network -------------------------------------------------------------

    def on_observation(
        self, session: RobotSession, index: int, capture_robot: float, arrays: dict[str, np.ndarray], recv: float
    ) -> bool:
        """Store the latest observation and update the mirror. Returns False if it was older than
        the latest (reordered) and ignored. Raises ValueError if the index went backwards."""
        with self.cond:
            mirror = session.mirror
            mirror.estimator.seed_offset(capture_robot, recv)  # only until the first clock sync
            if not mirror.on_observation(index, capture_robot, recv):
                return False
            session.latest = arrays
            session.observations += 1
            if mirror.is_useful():
                self.cond.notify_all()
            return True

    def on_clock_sync(self, session: RobotSession, msg: pb.ClockSync) -> None:
        with self.cond:
            session.mirror.estimator.add_exchange(
                msg.client_send_time, msg.server_recv_time, msg.server_send_time, msg.client_recv_time
            )

    def on_report(self, session: RobotSession, report: pb.ExecutionReport) -> None:
        """Fold an execution report into the mirror (delay exchanges) and the counters."""
        with self.cond:
            mirror = session.mirror
            for receipt in report.chunks:
                record = session.sent.pop(receipt.chunk_id, None)
                if record is None:
                    continue
                mirror.on_report(receipt.chunk_id, record.capture_robot, record.obs_recv, record.send_time, receipt.arrival_time)
                key = "unused" if receipt.first_executed_index < 0 else str(receipt.first_executed_index)
                session.first_executed[key] += 1
            session.reported_executed = int(report.executed_steps)
            session.reported_starved = int(report.starved_steps)
            session.reported_index = int(report.index)
            if mirror.obs_index is not None and math.isfinite(report.report_time):
                predicted = mirror.predicted_index(mirror.estimator.to_server_time(report.report_time))
                session.index_error = abs(predicted - int(report.index))

    # ---- the serving loop's side -------------------------------------------------------------

    def record_sent(self, session: RobotSession, chunk: Chunk, capture_robot: float, obs_recv: float, send_time: float) -> None:
        session.sent[chunk.chunk_id] = ChunkRecord(capture_robot, obs_recv, send_time)
        # Keep the table bounded for robots that never report.
        if len(session.sent) > 64:
            session.sent.pop(next(iter(session.sent)))
        session.chunks_sent += 1
        session.last_chunk_time = send_time

    def stop(self) -> None:
        with self.cond:
            self.stopping = True
            self.cond.notify_all()
