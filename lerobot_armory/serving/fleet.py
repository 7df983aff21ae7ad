"""The server's fleet state: one session per registered robot, each with its mirror.

Every mutation happens under one condition variable (``Fleet.cond``), shared by the network
threads (which feed observations and reports) and the serving loop (which reads the mirrors,
dispatches batches and delivers chunks). Holding it is always short: decoding happens before, and
inference after, the lock.
"""

from __future__ import annotations

import collections

import hmac
import math
import threading
import uuid
from collections.abc import Callable

import numpy as np

from lerobot_armory.feature_spec import FeatureSpec
from lerobot_armory.mirror import MAX_AWAITING_REPORTS, RobotMirror
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.serving.messages import ClockSync, ExecutionReport, Grant, Notice, NoticeKind, SyncRequest
from lerobot_armory.serving.outbox import MAX_NOTICE_CHARS
from lerobot_armory.serving.session import Link, RobotSession

# A registration that has not opened its stream within this long is dropped (and, when the fleet
# is full, the oldest such registration makes room for a new one at once).
STALE_SESSION_S = 5.0
# A slot is held by a robot that asks: when the fleet is full, a streaming robot that has sent no
# observation for this long (a socket held open, a robot stopped) gives its slot to a newcomer. It
# is told why and may register again. A robot that asks at 1 Hz or faster never comes near it.
IDLE_SESSION_S = 10.0
# Clock exchanges the server starts itself: one at stream start, then every SYNC_INTERVAL_S; a
# suspected clock step asks again at once (at most once per SYNC_MIN_GAP_S).
SYNC_INTERVAL_S = 10.0
SYNC_MIN_GAP_S = 1.0
MAX_PENDING_SYNCS = 4
# Each receipt of an execution report names a chunk its mirror awaits (at most
# MAX_AWAITING_REPORTS), so a report's first SENT_TABLE receipts are all that can mean anything.
SENT_TABLE = MAX_AWAITING_REPORTS
# Device time accounting for the grant rules's max_device_share: a decayed sum over this window.
SHARE_WINDOW_S = 5.0


class FleetError(Exception):
    """A request the fleet refuses; ``code`` names the gRPC status to answer with."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class Fleet:
    """All sessions, in registration order, behind one condition variable."""

    def __init__(
        self,
        clock: Callable[[], float],
        max_robots: int = 64,
        stale_session_s: float = STALE_SESSION_S,
        idle_session_s: float = IDLE_SESSION_S,
        history_steps: int = 1,
    ) -> None:
        self.clock = clock
        # Observations each session keeps (the engine's ``history_steps``; 1: the latest only).
        self.history_steps = history_steps
        self.max_robots = max_robots
        self.stale_session_s = stale_session_s
        self.idle_session_s = idle_session_s
        self.evicted_idle = 0  # streaming sessions that gave their slot to a newcomer
        self.cond = threading.Condition()
        self.sessions: dict[str, RobotSession] = {}
        self.stopping = False
        self.in_flight: set[str] = set()  # session ids in the batch the serving loop is running

    # ---- membership --------------------------------------------------------------------------

    def register(
        self,
        spec: RobotSpec,
        task: str,
        features: dict[str, FeatureSpec],
        credential: bytes | None = None,
        grant: Grant | None = None,
        register_recv: float | None = None,
        policy: str | None = None,
    ) -> RobotSession:
        """Add a robot. A robot id already *streaming* is refused; a stale registration of the
        same id (never streamed, or its stream ended) is replaced.

        A slot is held by a robot that streams and asks, on every entrypoint alike: registrations
        that never open a stream expire after ``stale_session_s``, and a full fleet drops the
        oldest of them to make room; failing that, the streaming robot that has sent no
        observation for the longest, if that is over ``idle_session_s`` (so squatting the slots,
        with registrations or with idle streams, buys nothing). Only a fleet full of robots that
        ask refuses (``RESOURCE_EXHAUSTED``)."""
        with self.cond:
            if self.stopping:
                raise FleetError("UNAVAILABLE", "the server is shutting down")
            for sid, s in list(self.sessions.items()):
                if s.robot_id == spec.robot_id:
                    if s.link.streaming:
                        raise FleetError("ALREADY_EXISTS", f"robot id {spec.robot_id!r} is already connected")
                    self._drop(sid)
            self._expire_unstreamed()
            now = self.clock()
            if len(self.sessions) >= self.max_robots:
                self._make_room(now)
            link = Link(credential=credential, grant=grant)
            session = RobotSession(uuid.uuid4().hex, spec, task, features, RobotMirror(spec), now, link=link)
            if policy is not None:
                session.policy = policy
            if self.history_steps > 1:
                session.recent = collections.deque(maxlen=self.history_steps)
            session.clock.register_stamps = (now if register_recv is None else register_recv, now)
            self.sessions[session.session_id] = session
            return session

    def attach(self, session_id: str, credential: bytes | None = None) -> RobotSession:
        """Mark a session's stream open (one stream per session, by the credential that
        registered it)."""
        with self.cond:
            session = self.sessions.get(session_id)
            if session is None:
                raise FleetError("FAILED_PRECONDITION", "unknown or expired session: call Register first")
            if session.link.credential is not None and not hmac.compare_digest(session.link.credential, credential or b""):
                raise FleetError("PERMISSION_DENIED", "this session was registered with another credential")
            if session.link.streaming:
                raise FleetError("ALREADY_EXISTS", f"robot {session.robot_id!r} already has an open stream")
            session.link.streaming = True
            return session

    def quarantine(self, session: RobotSession, reason: str) -> None:
        """End one robot's session because of something it sent (never the loop's problem): it
        is told why, its stream closes, and it may register again."""
        with self.cond:
            if self.sessions.get(session.session_id) is not session:
                return
            session.outbox.put(Notice(NoticeKind.DROPPED, reason[:MAX_NOTICE_CHARS]))
            self._drop(session.session_id)
            self.cond.notify_all()

    def release(self, robot_id: str, reason: str = "moved to another replica by the cluster") -> bool:
        """Move a robot away between two of its chunks (a cluster's rebalancing).

        The robot is told ``MOVED`` and its stream ends; it keeps the chunks it holds (they answer
        its own observations) and re-registers with its front. A robot whose request is in the
        batch now running is moved right after that chunk is queued. False: no such robot streams.
        """
        with self.cond:
            session = next((s for s in self.active() if s.robot_id == robot_id), None)
            if session is None:
                return False
            if session.session_id in self.in_flight:
                session.move_after_chunk = True
            else:
                self.move_now(session, reason)
            return True

    def move_now(self, session: RobotSession, reason: str = "moved to another replica by the cluster") -> None:
        """Tell ``session`` it moves and end it (lock held)."""
        session.outbox.put(Notice(NoticeKind.MOVED, reason[:MAX_NOTICE_CHARS]))
        self._drop(session.session_id)
        self.cond.notify_all()

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
            if not s.link.streaming and now - s.registered_at > self.stale_session_s:
                self._drop(sid)

    def _make_room(self, now: float) -> None:
        """Free one slot for a newcomer, or refuse it (lock held; see :meth:`register`)."""
        waiting = [sid for sid, s in self.sessions.items() if not s.link.streaming]
        if waiting:
            self._drop(waiting[0])  # dicts keep insertion order: the oldest registration
            return
        idle = [
            (now - (s.mirror.obs_recv if s.mirror.obs_index is not None else s.registered_at), s)
            for s in self.sessions.values()
            if s.session_id not in self.in_flight
        ]
        quiet_s, quietest = max(idle, key=lambda pair: pair[0], default=(0.0, None))
        if quietest is None or quiet_s <= self.idle_session_s:
            raise FleetError("RESOURCE_EXHAUSTED", f"the server already serves {self.max_robots} robots (--max_robots); retry later")
        quietest.outbox.put(
            Notice(
                NoticeKind.DROPPED,
                f"your session sent no observation for {quiet_s:.0f} s and the server is full: its slot went to "
                "another robot; register again",
            )
        )
        self._drop(quietest.session_id)
        self.evicted_idle += 1
        self.cond.notify_all()

    def active(self) -> list[RobotSession]:
        """Sessions with an open stream, in registration order (call with the lock held)."""
        return [s for s in self.sessions.values() if s.link.streaming]

    # ---- events from the network -------------------------------------------------------------

    def on_observation(
        self,
        session: RobotSession,
        index: int,
        capture_robot: float,
        arrays: dict[str, np.ndarray],
        recv: float,
        episode: int = 0,
    ) -> bool:
        """Store the latest observation and update the mirror. Returns False if it was older than
        the latest (reordered) and ignored. Raises ValueError if the index or episode went backwards.

        At an episode boundary the observation history and RTC's kept chunks belong to the old
        world: both are dropped with the mirror's queue.
        """
        with self.cond:
            mirror = session.mirror
            mirror.estimator.seed_offset(capture_robot, recv)  # only until the first clock sync
            before = mirror.episode
            if not mirror.on_observation(index, capture_robot, recv, episode):
                return False
            if mirror.episode != before:
                session.model_chunks.clear()
                if session.recent is not None:
                    session.recent.clear()
            session.latest = arrays
            if session.recent is not None:
                session.remember(index, arrays)
            session.counters.observations += 1
            if mirror.is_useful():
                self.cond.notify_all()
            return True

    def on_clock_sync(self, session: RobotSession, msg: ClockSync, recv: float) -> str | None:
        """Fold a clock exchange in; returns why it was refused (None: taken).

        The server side of an exchange is always the server's own stamps (those of the
        registration, or of the ClockSyncRequest answered), never the times the robot echoes.
        """
        a, r = msg.client_send_time, msg.client_recv_time
        if not (math.isfinite(a) and math.isfinite(r)):
            return "clock sync refused: a time is not a finite number"
        with self.cond:
            estimator = session.mirror.estimator
            if msg.sync_id == 0:
                if session.clock.register_stamps is None:
                    return "clock sync refused: the registration exchange was already completed"
                (b, s), session.clock.register_stamps = session.clock.register_stamps, None
                verdict = estimator.add_exchange(a, b, s, r)
            else:
                sent = session.clock.pending.pop(int(msg.sync_id), None)
                if sent is None:
                    return f"clock sync refused: no pending request {msg.sync_id}"
                # Answer to our request: we sent at `sent`, the robot got it at r and answered at a,
                # we received at recv. In add_exchange's terms the robot "sent" a and "received" r.
                if a < r:
                    return "clock sync refused: the answer left before the request arrived"
                estimator.server_round_trip(recv - sent)
                verdict = estimator.add_exchange(a, recv, sent, r)
        if verdict == "refused":
            return "clock sync refused: its round trip is impossible"
        return None

    def sync_request(self, session: RobotSession, now: float) -> SyncRequest | None:
        """A ClockSyncRequest to send now, if one is due (stream start, every SYNC_INTERVAL_S,
        or at once after a suspected clock step), stamped with ``now``."""
        with self.cond:
            if session.mirror.needs_sync and now - session.clock.next_at + SYNC_INTERVAL_S >= SYNC_MIN_GAP_S:
                session.mirror.needs_sync = False
            elif now < session.clock.next_at:
                return None
            session.clock.next_at = now + SYNC_INTERVAL_S
            sync_id = session.clock.next_id
            session.clock.next_id += 1
            session.clock.pending[sync_id] = now
            while len(session.clock.pending) > MAX_PENDING_SYNCS:  # a robot that never answers
                session.clock.pending.pop(next(iter(session.clock.pending)))
            return SyncRequest(sync_id, now)

    def on_report(self, session: RobotSession, report: ExecutionReport, recv: float) -> int:
        """Fold an execution report into the mirror (delay exchanges) and the counters.

        Only the first ``SENT_TABLE`` receipts are read (no more chunks can be awaiting a report),
        so the fleet lock is held for a bounded time whatever the report's size. Returns how many
        receipts were refused as implausible.
        """
        receipts = [(int(c.chunk_id), float(c.arrival_time), int(c.first_executed_index)) for c in report.receipts[:SENT_TABLE]]
        refused = 0
        with self.cond:
            mirror = session.mirror
            for chunk_id, arrival, first in receipts:
                verdict = mirror.on_report(chunk_id, arrival, recv)
                if verdict is None:
                    continue  # not a chunk awaiting its report (unknown, repeated, or forgotten)
                refused += not verdict
                key = "unused" if first < 0 else str(min(first, session.spec.chunk_size))
                session.counters.first_executed[key] += 1
            session.counters.reported_executed = int(report.executed_steps)
            session.counters.reported_starved = int(report.starved_steps)
            session.counters.reported_index = int(report.index)
            if mirror.obs_index is not None:
                window = mirror.estimator.uplink_window_s()
                t = min(recv, max(recv - window, mirror.estimator.to_server_time(report.report_time)))
                session.counters.index_error = abs(mirror.predicted_index(t) - int(report.index))
        return refused

    # ---- device share (the grant rules's max_device_share) ----------------------------------

    def charge_device(self, sessions: list[RobotSession], seconds: float, t_end: float) -> None:
        """Book ``seconds`` of device time, split evenly, on the batch's robots (lock held)."""
        for session in sessions:
            self._decay(session, t_end)
            session.share.seconds += seconds / max(1, len(sessions))

    def over_share(self, session: RobotSession, now: float) -> bool:
        """Whether the robot used more than its granted share of device time lately (lock held).

        Both its device time and the wall time since it registered are summed with the same
        exponential decay (time constant SHARE_WINDOW_S), so the ratio is its recent share from
        the first second on, not only once a whole window has passed.
        """
        if session.link.grant is None or session.link.grant.max_device_share >= 1.0:
            return False
        self._decay(session, now)
        wall = SHARE_WINDOW_S * -math.expm1(-max(0.0, now - session.registered_at) / SHARE_WINDOW_S)
        return session.share.seconds > session.link.grant.max_device_share * wall

    @staticmethod
    def _decay(session: RobotSession, now: float) -> None:
        if now > session.share.at:
            session.share.seconds *= math.exp(-(now - session.share.at) / SHARE_WINDOW_S)
            session.share.at = now

    # ---- the serving loop's side -------------------------------------------------------------

    def record_sent(self, session: RobotSession, send_time: float) -> None:
        """Count a chunk sent to ``session`` (its report is awaited by the mirror)."""
        session.counters.chunks_sent += 1
        session.counters.last_chunk_time = send_time

    def stop(self) -> None:
        with self.cond:
            self.stopping = True
            self.cond.notify_all()
