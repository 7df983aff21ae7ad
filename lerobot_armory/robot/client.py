"""``ArmoryClient``: the robot's control loop against an armory server.

At every tick (``fps``): capture the observation, push it to the server, then execute the action
for the current index from the newest arrived chunk covering it — or starve (nothing goes to the
motors, the index stays). Execution reports (what arrived when, what was executed first) go back
a few times a second so the server can estimate delays without synchronised clocks.

Losing the server never makes the robot act on stale data: the moment the stream breaks, every
buffered chunk is dropped and the robot holds (starves) while a background thread reconnects
with exponential back-off, registers again and resumes. Chunks of an earlier session are
recognised by their session epoch and never executed.

Episodes: a robot whose world resets (a new task attempt, a simulator's next episode) calls
:meth:`ArmoryClient.new_episode` before its next tick. Every chunk held is dropped at once (the
old world's plan must never move the new one), observations carry the new episode number, the
server serves the first observation of the episode without waiting ``h_min`` steps, and a chunk
computed from an older episode's observation that arrives afterwards is dropped, never executed.

Against a cluster (``lerobot-armory-cluster``) ``address`` is the front: registration answers
with the replica to stream to and the connection follows it. When that replica dies the robot
holds as above and registers with the front again, which places it on a live replica. When the
cluster *moves* the robot (a ``MOVED`` notice, sent between two of its chunks) nothing is stale:
the robot keeps executing the chunks it holds while it re-registers.

The loop is independent of any hardware: it takes ``observe()`` and ``act(action)`` callables,
so a LeRobot robot, a simulated robot or a test double plug in the same way.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import grpc
import numpy as np

from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.robot.actions import ActionBuffer
from lerobot_armory.robot.connection import Connection, ReceivedChunk, Registration
from lerobot_armory.robot.netem import NetworkEmulator

log = logging.getLogger(__name__)

REPORT_EVERY_S = 0.2
# Registration answers that mean "try again later" rather than "you are wrong". RESOURCE_EXHAUSTED:
# the server is full (--max_robots, or slots held by registrations that never streamed and expire):
# a slot frees up when another robot leaves, so the robot waits its turn instead of exiting.
RETRYABLE = (
    grpc.StatusCode.UNAVAILABLE,
    grpc.StatusCode.DEADLINE_EXCEEDED,
    grpc.StatusCode.ALREADY_EXISTS,
    grpc.StatusCode.RESOURCE_EXHAUSTED,
)


class RegistrationRefused(RuntimeError):
    """The server refused the registration; the message is the server's reason."""


@dataclass
class RobotIdentity:
    """What the robot tells the server at registration."""

    robot_id: str
    fps: float
    h_min: int
    h_max: int
    weight: float = 1.0
    tier: str = "slow"
    task: str = ""
    policy_name: str = ""  # the policy to be served by, where the server serves several


@dataclass
class Backoff:
    """Reconnection delays: ``initial_s``, doubling up to ``max_s``; ``give_up_s`` 0 = never."""

    initial_s: float = 0.5
    max_s: float = 5.0
    give_up_s: float = 0.0


class ArmoryClient:
    """Runs one robot's control loop against a server.

    Args:
        address: server ``host:port``.
        identity: robot id, rate, horizons, weight, tier, task.
        features: observation features ``{name: (dtype, shape)}`` the robot sends.
        observe: returns the current observation ``{name: array}``.
        act: sends one action to the motors.
        clock / sleep: injectable for tests.
        jpeg_quality: JPEG-encode uint8 images on the wire (None: raw bytes).
        backoff: reconnection policy.
        network: factory of an emulated network per connection (benchmarks).
        tls_ca / token: TLS trust root and auth token (see docs/security.md).
        check_registration: called with the server's answer to every registration (reconnects
            included: a restarted server may serve another policy) before the stream opens; it
            raises :class:`RegistrationRefused` to refuse the policy, and the session is then
            given back at once, before a single chunk can arrive.
        record_actions: keep ``(time, session epoch of the chunk, chunk_id, chunk i_start, index)``
            of every executed action in ``executed_log`` (tests and failover checks).
        episode_of: the robot's own episode counter, read after every observation; when it
            changes, :meth:`new_episode` is called before the observation is sent (a simulator
            that resets itself; None: only explicit :meth:`new_episode` calls).
        finished: :meth:`run` returns once it is True (e.g. a simulator ran its last episode).
    """

    def __init__(
        self,
        address: str,
        identity: RobotIdentity,
        features: Mapping[str, tuple[str, tuple[int, ...]]],
        observe: Callable[[], Mapping[str, np.ndarray]],
        act: Callable[[np.ndarray], None],
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        jpeg_quality: int | None = None,
        backoff: Backoff | None = None,
        network: Callable[[], NetworkEmulator] | None = None,
        tls_ca: bytes | None = None,
        token: str = "",
        check_registration: Callable[[Registration], None] | None = None,
        record_actions: bool = False,
        episode_of: Callable[[], int] | None = None,
        finished: Callable[[], bool] | None = None,
    ) -> None:
        self.address = address
        self.identity = identity
        self.features = dict(features)
        self.observe = observe
        self.act = act
        self.clock = clock
        self.sleep = sleep
        self.jpeg_quality = jpeg_quality
        self.backoff = backoff or Backoff()
        self.network = network
        self.tls_ca = tls_ca
        self.token = token
        self.check_registration = check_registration
        self.episode_of = episode_of
        self._robot_episode = episode_of() if episode_of is not None else 0
        self.finished = finished
        self.buffer = ActionBuffer(identity.h_max)
        self._lock = threading.Lock()
        self._epoch = 0
        self._moving = False  # a MOVED notice came: the held chunks stay valid through the re-registration
        self.connection: Connection | None = None
        self._reconnecting: threading.Thread | None = None
        self._stop = threading.Event()
        self.fatal: BaseException | None = None
        self.index = 0
        self.episode = 0
        self.stale_episode_chunks = 0  # chunks of an earlier episode that arrived after its end (dropped)
        self.ticks = 0
        self.executed = 0
        self.starved = 0
        self.reconnects = 0
        self.chunks_received = 0
        self.notices: list[str] = []
        self.policy: str = ""
        self.chunk_size: int = 0
        self.granted: pb.Grant | None = None  # the grant rules's grant of the current session, if the server sent one
        # Outages: seconds from a lost connection to the next executed action (holding meanwhile).
        self.outages: list[float] = []
        self._lost_at: float | None = None
        self.losses: list[tuple[float, int]] = []  # (robot time, session epoch) of every lost connection
        self.executed_log: list[tuple[float, int, int, int, int]] | None = [] if record_actions else None

    # ---- connection --------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self.connection is not None

    def connect(self) -> None:
        """Register and open the stream, retrying with back-off while the server is unreachable.

        Raises:
            RegistrationRefused: the server said no (the message is its reason).
            ConnectionError: ``backoff.give_up_s`` passed without reaching the server.
        """
        start = self.clock()
        delay = self.backoff.initial_s
        while not self._stop.is_set():
            try:
                self._connect_once()
                return
            except ConnectionError as exc:
                waited = self.clock() - start
                if self.backoff.give_up_s and waited + delay > self.backoff.give_up_s:
                    raise ConnectionError(f"{exc}; gave up after {waited:.1f} s") from None
                log.warning("%s; retrying in %.1f s", exc, delay)
                self._stop.wait(delay)
                delay = min(delay * 2, self.backoff.max_s)

    def _connect_once(self) -> None:
        conn = Connection(
            self.address, self.clock, network=self.network() if self.network else None, tls_ca=self.tls_ca, token=self.token
        )
        if not conn.wait_ready(timeout=2.0):
            conn.close()
            raise ConnectionError(f"server {self.address} is unreachable")
        ident = self.identity
        try:
            reg = conn.register(
                ident.robot_id, self.features, ident.fps, ident.h_min, ident.h_max, ident.weight, ident.tier, ident.task,
                policy_name=ident.policy_name,
            )  # fmt: skip
        except grpc.RpcError as exc:
            conn.close()
            if exc.code() in RETRYABLE:
                raise ConnectionError(f"server {self.address} busy or not ready: {exc.code().name}: {exc.details()}") from None
            raise RegistrationRefused(f"{exc.code().name}: {exc.details()}") from None
        try:
            h_max = self._accept_grant(reg.granted)
            if self.check_registration is not None:
                self.check_registration(reg)
        except RegistrationRefused:
            conn.end_session()
            raise
        with self._lock:
            self._epoch += 1
            epoch = self._epoch
            if not self._moving:
                self.buffer.clear()  # nothing from an earlier session may ever run
            self._moving = False
            self.buffer.session = epoch
            self.buffer.h_max = h_max  # a reconnect may be granted another horizon than the last session
            self.connection = conn
        self.policy, self.chunk_size, self.granted = reg.policy, reg.chunk_size, reg.granted
        conn.open_stream(
            lambda chunk: self._on_chunk(epoch, chunk),
            lambda notice: self._on_notice(notice, epoch),
            lambda error: self._on_close(epoch, error),
        )
        log.info("registered as %s with %s (H=%d), session %d", ident.robot_id, reg.policy, reg.chunk_size, epoch)

    def _accept_grant(self, granted: pb.Grant | None) -> int:
        """Log what the grant rules granted; returns the h_max the action buffer must use.

        The robot's weight, tier and horizons are requests the operator's policy may change: the
        robot follows the grant, since the server schedules by it. Its fps is not negotiable (the
        controller rate is physical), so a grant at another rate is refused.
        """
        ident = self.identity
        if granted is None:
            return ident.h_max  # a server without grant rules: the request is what it uses
        log.info(
            "granted by grant rules (%s): weight %g, tier %s, fps %g, h_min %d, h_max %d, device share %g",
            granted.rule or "no rule named", granted.weight, granted.tier, granted.fps, granted.h_min, granted.h_max,
            granted.max_device_share,
        )  # fmt: skip
        if not math.isclose(granted.fps, ident.fps, rel_tol=1e-9):
            raise RegistrationRefused(
                f"the server granted fps {granted.fps:g} but this robot runs at fps {ident.fps:g}: "
                "the control rate cannot change, fix --fps or the server's grant rules"
            )
        same_weight = math.isclose(granted.weight, ident.weight, rel_tol=1e-9)
        changed = [
            f"{name} asked {asked} granted {got}"
            for name, asked, got, same in (
                ("weight", f"{ident.weight:g}", f"{granted.weight:g}", same_weight),
                ("tier", ident.tier, granted.tier, granted.tier == ident.tier),
                ("h_min", ident.h_min, granted.h_min, granted.h_min == ident.h_min),
                ("h_max", ident.h_max, granted.h_max, granted.h_max == ident.h_max),
            )
            if not same
        ]
        if changed:
            rule = granted.rule or "no rule named"
            log.warning("the grant rules (%s) changed this robot's request: %s", rule, "; ".join(changed))
        # The server sends chunks for the granted horizon: executing beyond it would outrun what it
        # plans for. A larger grant is not taken either: h_max is also the robot's own safety limit.
        return min(ident.h_max, granted.h_max) if granted.h_max > 0 else ident.h_max

    def _on_chunk(self, epoch: int, chunk: ReceivedChunk) -> None:
        with self._lock:
            if epoch != self._epoch or self.connection is None:
                return  # a chunk of a dead session: never executed
            self.chunks_received += 1
            if chunk.episode != self.episode:
                # Computed from the old world: reported (its arrival is a delay sample) as never executed.
                self.stale_episode_chunks += 1
                self.buffer.add_unused(chunk.chunk_id, chunk.arrival_time)
                return
            self.buffer.add(chunk.chunk_id, chunk.i_start, chunk.actions, chunk.arrival_time)

    def new_episode(self) -> int:
        """The robot's world was reset: drop every chunk held and number the next observations
        with a new episode (see the module's docstring). Returns the new episode number."""
        with self._lock:
            self.episode += 1
            self.buffer.drop_chunks()
            return self.episode

    def _on_notice(self, notice: pb.Notice, epoch: int | None = None) -> None:
        self.notices.append(notice.message)
        if notice.kind == pb.Notice.MOVED:
            with self._lock:
                if epoch == self._epoch:
                    self._moving = True  # the stream's close that follows re-registers, keeping the buffer
        # SHUTDOWN and CLOCK are expected events (a reconnect or a sync request follows); DROPPED
        # (the server ended this session) is followed by the stream's close, which reconnects.
        level = logging.INFO if notice.kind in (pb.Notice.SHUTDOWN, pb.Notice.CLOCK, pb.Notice.MOVED) else logging.WARNING
        log.log(level, "server: %s", notice.message)

    def _on_close(self, epoch: int, error: grpc.RpcError | None) -> None:
        with self._lock:
            if epoch != self._epoch or self._stop.is_set():
                return
            lost, self.connection = self.connection, None
            if error is not None:
                self._moving = False  # a MOVED followed by a broken stream is a loss like any other
            if not self._moving:
                self.buffer.clear()  # hold: no stale actions while disconnected
                if self._lost_at is None:
                    self._lost_at = self.clock()
                self.losses.append((self.clock(), epoch))
        if self._moving:
            log.info("moved by the cluster: re-registering, executing the chunks held meanwhile")
        else:
            reason = f"{error.code().name}: {error.details()}" if error is not None else "stream closed by the server"
            log.warning("connection lost (%s); holding position and reconnecting", reason)
        if lost is not None:
            threading.Thread(target=lost.close, daemon=True).start()
        self._start_reconnect()

    def _start_reconnect(self) -> None:
        if self._reconnecting is not None and self._reconnecting.is_alive():
            return

        def run() -> None:
            try:
                self.connect()
                if self.connection is not None:
                    self.reconnects += 1
            except RegistrationRefused as exc:
                log.error("re-registration refused: %s", exc)
                self.fatal = exc
            except ConnectionError as exc:
                log.error("%s", exc)
                self.fatal = exc

        self._reconnecting = threading.Thread(target=run, name="armory-reconnect", daemon=True)
        self._reconnecting.start()

    # ---- the control loop --------------------------------------------------------------------

    def step(self) -> bool:
        """One control tick: observe, push, execute or starve. Returns True if it executed."""
        t = self.clock()
        obs = self.observe()
        if self.episode_of is not None and (e := self.episode_of()) != self._robot_episode:
            self._robot_episode = e
            self.new_episode()
        conn = self.connection
        if conn is not None:
            conn.send_observation(self.index, obs, capture_time=t, jpeg_quality=self.jpeg_quality, episode=self.episode)
        with self._lock:
            live = self.connection is not None or self._moving
            action = self.buffer.action_for(self.index) if live else None
            chunk = self.buffer.current
        self.ticks += 1
        if action is None:
            self.starved += 1
            return False
        if self._lost_at is not None:
            self.outages.append(self.clock() - self._lost_at)
            self._lost_at = None
        if self.executed_log is not None and chunk is not None:
            self.executed_log.append((t, chunk.session, chunk.chunk_id, chunk.i_start, self.index))
        self.act(action)
        self.index += 1
        self.executed += 1
        return True

    def report(self) -> None:
        """Send an execution report with every chunk receipt not yet reported."""
        conn = self.connection
        if conn is None:
            return
        with self._lock:
            receipts = self.buffer.take_receipts(self._epoch)
        conn.send_report(self.index, self.executed, self.starved, receipts)

    def run(self, duration_s: float = 0.0) -> dict[str, Any]:
        """Connect if needed, then tick at ``fps`` for ``duration_s`` (0: until :meth:`stop`).

        Raises RegistrationRefused / ConnectionError if the server refuses or cannot be reached
        (at start, or when reconnecting gives up).
        """
        if self.connection is None:
            self.connect()
        period = 1.0 / self.identity.fps
        start = self.clock()
        next_tick = start
        last_report = start
        while not self._stop.is_set():
            if self.fatal is not None:
                raise self.fatal
            now = self.clock()
            if (duration_s and now - start >= duration_s) or (self.finished is not None and self.finished()):
                break
            if now < next_tick:
                self.sleep(min(next_tick - now, 0.05))
                continue
            self.step()
            if now - last_report >= REPORT_EVERY_S:
                self.report()
                last_report = now
            next_tick += period
            if self.clock() - next_tick > period:  # overran: do not burst to catch up
                next_tick = self.clock()
        self.report()
        return self.stats()

    def stop(self) -> None:
        """Ask :meth:`run` to return after the current tick."""
        self._stop.set()

    def close(self) -> None:
        """Stop and close the connection."""
        self._stop.set()
        with self._lock:
            conn, self.connection = self.connection, None
            self._epoch += 1
            self.buffer.clear()  # chunks never executed are accounted as unused
        if conn is not None:
            conn.close()

    def stats(self) -> dict[str, Any]:
        """The stats JSON of the run so far."""
        with self._lock:
            first = dict(self.buffer.first_executed_index)
            seams = self.buffer.seam_stats()
        return {
            "robot_id": self.identity.robot_id,
            "tier": self.identity.tier,
            "ticks": self.ticks,
            "executed_steps": self.executed,
            "starved_steps": self.starved,
            "starvation_pct": 100.0 * self.starved / self.ticks if self.ticks else 0.0,
            "chunks_received": self.chunks_received,
            "episodes": self.episode + 1,
            "stale_episode_chunks": self.stale_episode_chunks,
            "first_executed_index": first,
            "reconnects": self.reconnects,
            "outages_s": list(self.outages),
            **seams,
        }
