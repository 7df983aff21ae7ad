"""The gRPC front end: registration, one bidirectional stream per robot, health checking.

Each stream has a reader thread that decodes and validates the robot's messages and feeds the
fleet, while the RPC's own thread writes what the serving loop put in the robot's outbox. A bad
message gets a ``Notice`` saying why and is dropped; the stream, the server and every other robot
go on. Nothing from the wire is unpickled, evaluated or used as a path.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Iterator
from concurrent import futures
from dataclasses import dataclass

import grpc
import numpy as np
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from lerobot_armory.errors import ConfigError
from lerobot_armory.robot_spec import spec_problems
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import ArmoryAdminServicer, ArmoryServicer
from lerobot_armory.entrypoints.grpc.hardening import Malformed, add_admin_to_server, add_armory_to_server
from lerobot_armory.entrypoints.grpc.translate import clock_sync_from_wire, grant_to_wire, report_from_wire, to_wire
from lerobot_armory.proto.limits import (
    FORWARD_PROOF_KEY,
    FORWARDED_FOR_KEY,
    SERVER_KEEPALIVE_OPTIONS,
    SERVICE_NAME,
    SESSION_KEY,
    TOKEN_KEY,
)
from lerobot_armory.serving.admission import AdmissionLimiter, peer_host
from lerobot_armory.serving.forwarding import ForwardingKey
from lerobot_armory.serving.fleet import SENT_TABLE, Fleet, FleetError
from lerobot_armory.serving.session import DEFAULT_POLICY, RobotSession
from lerobot_armory.serving.messages import Notice, NoticeKind
from lerobot_armory.serving.outbox import MAX_NOTICE_CHARS
from lerobot_armory.serving.grant_rules import GrantRules, GrantRequest, describe_grant
from lerobot_armory.serving.peer_log import ThrottledLog
from lerobot_armory.serving.registration import Registrar, Registration
from lerobot_armory.serving.security import RateLimiter
from lerobot_armory.wire import FeatureSpec, WireError, check_features, decode_all, spec_from_proto, specs_to_proto

log = logging.getLogger(__name__)

MAX_TASK = 4096
# How often a stream's writer wakes to send a due clock-sync request when nothing else is queued.
SYNC_POLL_S = 0.2


@dataclass(frozen=True)
class PolicyInfo:
    """What registration checks against and tells the robot."""

    description: str
    wire_features: list[FeatureSpec]
    action_names: list[str]
    chunk_size: int


class ArmoryService(ArmoryServicer):
    """Implements ``Register`` and ``Stream`` over a :class:`Fleet`."""

    def __init__(
        self,
        fleet: Fleet,
        policy: PolicyInfo,
        max_message_bytes: int,
        registrar: Registrar | None = None,
        max_obs_rate_hz: float = 0.0,
        policy_name: str = DEFAULT_POLICY,
        others: dict[str, PolicyInfo] | None = None,
    ) -> None:
        self.fleet = fleet
        # Credentials, admission and grants: the one registration path, shared with openpi.
        self.registrar = registrar or Registrar(fleet, GrantRules.builtin(), AdmissionLimiter())
        self.policy = policy  # the first policy's (a swap replaces it)
        self.policy_name = policy_name
        self.others = dict(others or {})  # more policies served from the same device, by name
        self.max_message_bytes = max_message_bytes
        self.max_obs_rate_hz = max_obs_rate_hz
        self.peer_log = ThrottledLog(log)  # one line per misbehaving peer per 10 s, no tracebacks
        # A cluster replica's: the key its front proves forwarded hosts with (None: a single server,
        # which counts every registration against its own peer).
        self.forwarding: ForwardingKey | None = None

    # ---- Register ----------------------------------------------------------------------------

    def Register(self, request: pb.RegisterRequest, context: grpc.ServicerContext) -> pb.RegisterResponse:  # noqa: N802
        recv = self.fleet.clock()
        if isinstance(request, Malformed):
            self.peer_log.warn(context.peer(), f"malformed RegisterRequest ({request.size} bytes): {request.error}")
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "malformed RegisterRequest")
        try:
            credential = self.registrar.authenticate(request.robot_id, request.auth_token)
            self.registrar.admit(self._admitted_host(request.robot_id, context), credential)
        except FleetError as exc:
            if exc.code == "RESOURCE_EXHAUSTED":
                self.peer_log.warn(context.peer(), str(exc))
            context.abort(getattr(grpc.StatusCode, exc.code), str(exc))
        name, info, problems = self._policy_for(request.policy_name)
        if info is not None:
            problems = self._check_registration(request, info)
        asked = GrantRequest(request.robot_id, request.fps, request.h_min, request.h_max, request.weight, request.tier)
        try:
            if info is None:
                raise FleetError("INVALID_ARGUMENT", "registration refused: " + "; ".join(problems))
            # Features are read only from a request without problems (a bad shape is one of them).
            features = {} if problems else {f.name: spec_from_proto(f) for f in request.features}
            registration = Registration(asked, info.chunk_size, features, request.task, name, tuple(problems))
            session, grant = self.registrar.register(registration, credential, recv)
        except FleetError as exc:
            context.abort(getattr(grpc.StatusCode, exc.code), str(exc))
        spec = session.spec
        if self.max_obs_rate_hz > 0:
            session.link.obs_rate = RateLimiter(self.max_obs_rate_hz)
        log.info(
            "registered %s (tier=%s weight=%g fps=%g h=[%d,%d]; %s) task=%r%s",
            spec.robot_id, spec.tier, spec.weight, spec.fps, spec.h_min, spec.h_max, describe_grant(asked, grant),
            request.task[:80], f" policy={name}" if self.others else "",
        )  # fmt: skip
        assert session.clock.register_stamps is not None
        return pb.RegisterResponse(
            session_id=session.session_id,
            action_names=info.action_names,
            chunk_size=info.chunk_size,
            action_dim=len(info.action_names),
            server_recv_time=session.clock.register_stamps[0],
            server_send_time=session.clock.register_stamps[1],
            policy=info.description,
            expected_features=specs_to_proto(info.wire_features),
            max_message_bytes=self.max_message_bytes,
            granted=grant_to_wire(grant),
        )

    def _admitted_host(self, robot_id: str, context: grpc.ServicerContext) -> str:
        """The host a registration counts against: the robot's own when this replica's front names
        it with a valid proof (serving/forwarding.py), else the peer's (a single server: always)."""
        peer = peer_host(context.peer())
        if self.forwarding is None:
            return peer
        metadata = dict(context.invocation_metadata())
        named = metadata.get(FORWARDED_FOR_KEY)
        if not isinstance(named, str):
            return peer
        proof = metadata.get(FORWARD_PROOF_KEY)
        if isinstance(proof, str) and self.forwarding.verify(named, robot_id, proof):
            return named
        # Neither the host named nor the proof is echoed: what a peer sends is not logged verbatim.
        self.peer_log.warn(
            context.peer(), "registration names a forwarded host without the front's proof: counted against this peer"
        )
        return peer

    def _policy_for(self, asked: str) -> tuple[str, PolicyInfo | None, list[str]]:
        """The policy a registration names: (name, its info, []) or (asked, None, [why not])."""
        served = {self.policy_name: self.policy, **self.others}
        if not asked and len(served) == 1:
            return self.policy_name, self.policy, []
        names = ", ".join(repr(n) for n in served)
        if not asked:
            return asked, None, [f"policy_name: this server serves several policies ({names}); name one (--policy_name=NAME)"]
        info = served.get(asked)
        if info is None:
            return asked, None, [f"policy_name: no policy named {asked[:80]!r}; this server serves {names}"]
        return asked, info, []

    def _check_registration(self, r: pb.RegisterRequest, info: PolicyInfo) -> list[str]:
        """Every problem with a registration for the policy ``info`` (empty: accepted)."""
        # RobotSpec's own validator, against the policy's chunk size: every problem, not the first.
        problems = spec_problems(r.robot_id, r.fps, info.chunk_size, r.h_min, r.h_max, r.weight, r.tier)
        if len(r.task) > MAX_TASK:
            problems.append(f"task: text is longer than {MAX_TASK} characters")
        declared = []
        for f in r.features:
            if any(d < 0 for d in f.shape) or len(f.shape) > 8:
                problems.append(f"feature {f.name!r}: invalid shape {list(f.shape)}")
            else:
                declared.append(spec_from_proto(f))
        problems += check_features(declared, info.wire_features)
        return problems

    # ---- Stream ------------------------------------------------------------------------------

    def Stream(self, request_iterator: Iterator[pb.RobotMessage], context: grpc.ServicerContext) -> Iterator[pb.ServerMessage]:  # noqa: N802
        metadata = dict(context.invocation_metadata())
        session_id = metadata.get(SESSION_KEY, "")
        credential = None
        if self.registrar.auth is not None:
            with self.fleet.cond:
                known = self.fleet.sessions.get(session_id)
            try:
                if known is None:
                    raise FleetError("UNAUTHENTICATED", "missing or wrong auth token")
                credential = self.registrar.authenticate(known.robot_id, metadata.get(TOKEN_KEY, ""), "auth token")
            except FleetError as exc:
                context.abort(grpc.StatusCode.UNAUTHENTICATED, str(exc))
        try:
            session = self.fleet.attach(session_id, credential.digest if credential else None)
        except FleetError as exc:
            context.abort(getattr(grpc.StatusCode, exc.code), str(exc))
        log.info("stream open: %s", session.robot_id)
        reader = threading.Thread(
            target=self._read, args=(session, request_iterator, context.peer()), name=f"armory-read-{session.robot_id}", daemon=True
        )
        reader.start()
        context.add_callback(session.outbox.close)  # client went away: stop writing
        try:
            while True:
                # Stamped the moment it is handed to gRPC: the server side of the exchange is ours.
                sync = self.fleet.sync_request(session, self.fleet.clock())
                if sync is not None:
                    yield to_wire(sync)
                msg = session.outbox.get(timeout=SYNC_POLL_S)
                if msg is None:
                    if session.outbox.closed:
                        return
                    if not context.is_active():
                        return
                    continue
                yield to_wire(msg)
        finally:
            self.fleet.detach(session.session_id)
            log.info("stream closed: %s (its state is dropped)", session.robot_id)

    def _read(self, session: RobotSession, requests: Iterator[pb.RobotMessage | Malformed], peer: str) -> None:
        """Consume one robot's messages until its stream ends."""
        try:
            for msg in requests:
                if isinstance(msg, Malformed):
                    self._throttled_notice(session, f"malformed message ignored ({msg.size} bytes)")
                    self.peer_log.warn(peer, f"{session.robot_id}: malformed message ignored ({msg.size} bytes): {msg.error}")
                    continue
                kind = msg.WhichOneof("kind")
                if kind == "observation":
                    self._observation(session, msg.observation)
                elif kind == "report":
                    self._report(session, msg.report)
                elif kind == "clock_sync":
                    problem = self.fleet.on_clock_sync(session, clock_sync_from_wire(msg.clock_sync), self.fleet.clock())
                    if problem is not None:
                        self._notice(session, NoticeKind.CLOCK, problem)
                else:
                    self._notice(session, NoticeKind.INFO, "empty message ignored")
        except grpc.RpcError:
            pass  # the stream died (client gone, cancelled): the writer side cleans up
        except Exception:  # pragma: no cover - a bug must not take the server down
            log.exception("reader for %s failed", session.robot_id)
        finally:
            session.outbox.close()

    def _observation(self, session: RobotSession, obs: pb.Observation) -> None:
        recv = self.fleet.clock()
        if session.link.obs_rate is not None and not session.link.obs_rate.allow():
            session.counters.rejected += 1
            self._throttled_notice(
                session, f"observation rate above the server's limit of {self.max_obs_rate_hz:g} Hz: observations dropped",
                NoticeKind.REJECTED_OBSERVATION, obs.index,
            )  # fmt: skip
            return
        try:
            if not math.isfinite(obs.capture_time):
                raise WireError("capture_time is not a finite number")
            if obs.index < 0:
                raise WireError(f"index must be >= 0, got {obs.index}")
            arrays = decode_all(obs.tensors, session.features)
            for name, arr in arrays.items():
                if arr.dtype.kind == "f" and not np.isfinite(arr).all():
                    raise WireError(f"{name} contains NaN or inf")
            self.fleet.on_observation(session, int(obs.index), float(obs.capture_time), arrays, recv, int(obs.episode))
        except (WireError, ValueError) as exc:
            session.counters.rejected += 1
            self._notice(session, NoticeKind.REJECTED_OBSERVATION, f"observation {obs.index} dropped: {exc}", obs.index)

    def _report(self, session: RobotSession, report: pb.ExecutionReport) -> None:
        recv = self.fleet.clock()
        if not session.link.report_rate.allow():
            return  # a robot reports a few times a second; a flood is dropped before any work
        if not math.isfinite(report.report_time) or report.executed_steps < 0 or report.starved_steps < 0:
            self._notice(session, NoticeKind.REJECTED_REPORT, "execution report dropped: non-finite time or negative counts")
            return
        read = report.chunks[:SENT_TABLE]
        if any(not math.isfinite(c.arrival_time) for c in read):
            self._notice(session, NoticeKind.REJECTED_REPORT, "execution report dropped: non-finite chunk arrival time")
            return
        if len(report.chunks) > SENT_TABLE:
            self._notice(
                session, NoticeKind.REJECTED_REPORT,
                f"execution report has {len(report.chunks)} receipts; only the first {SENT_TABLE} were read",
            )  # fmt: skip
        refused = self.fleet.on_report(session, report_from_wire(report, SENT_TABLE), recv)
        if refused:
            self._notice(session, NoticeKind.CLOCK, f"{refused} chunk arrival time(s) implausible for the server's clock: not used")

    def _throttled_notice(self, session: RobotSession, message: str, kind: NoticeKind = NoticeKind.INFO, index: int = -1) -> None:
        """A notice for a flood (rate limit, garbage): one a second, not one per message."""
        now = self.fleet.clock()
        if now - session.link.notified_at > 1.0:
            session.link.notified_at = now
            self._notice(session, kind, message, index)

    @staticmethod
    def _notice(session: RobotSession, kind: NoticeKind, message: str, index: int = -1) -> None:
        # Cut: a message can echo what the robot sent (a tensor name), and notices wait in memory.
        text = message if len(message) <= MAX_NOTICE_CHARS else message[: MAX_NOTICE_CHARS - 3] + "..."
        session.outbox.put(Notice(kind, text, index))


@dataclass
class RunningServer:
    """A started gRPC server with its health servicer."""

    server: grpc.Server
    port: int
    health: health.HealthServicer

    def set_serving(self, serving: bool) -> None:
        status = health_pb2.HealthCheckResponse.SERVING if serving else health_pb2.HealthCheckResponse.NOT_SERVING
        for name in ("", SERVICE_NAME):
            self.health.set(name, status)


# A client gets this long from TCP accept to its HTTP/2 SETTINGS (the TLS handshake included).
# gRPC's default is 120 s: 1,100 sockets that connect and send nothing held their fds for two
# minutes and, at the common 1024 fd limit, kept every new robot out for that long. A robot on a
# slow link needs well under a second; 5 s leaves room for a loaded server.
HANDSHAKE_TIMEOUT_MS = 5_000
# A connection with no RPC on it for this long is closed (GOAWAY). gRPC counts a robot's stream as
# an RPC however quiet it is, so this only closes connections that hold nothing; a robot's channel
# reconnects by itself on its next call.
MAX_CONNECTION_IDLE_MS = 60_000
# Connections open at once (handshaking or not); gRPC closes those over it at accept. Capped below
# the fd limit so that a flood of connections leaves fds to the rest of the process (model files,
# logs, the metrics server); a fleet needs one per robot plus a few probes.
MAX_INCOMING_CONNECTIONS = 4096
FD_RESERVE = 256


def raise_fd_limit() -> int:
    """Raise this process's soft limit on open files to its hard limit (best effort).

    Returns:
        The soft limit in force afterwards (-1: unknown, e.g. no ``resource`` module).
    """
    try:
        import resource  # POSIX only: imported here so that the module loads everywhere
    except ImportError:
        return -1
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    # an unlimited hard limit is not a soft value every system takes (macOS caps files per process)
    target = 1 << 20 if hard == resource.RLIM_INFINITY else hard
    if soft == resource.RLIM_INFINITY or soft >= target:
        return target
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    except (ValueError, OSError) as exc:
        log.warning("could not raise the open-file limit from %d to %d: %s", soft, target, exc)
        return soft
    return target


def _connection_cap(max_robots: int, fd_limit: int) -> int:
    """Connections gRPC may hold: :data:`MAX_INCOMING_CONNECTIONS` (more for a big fleet), below the fd limit."""
    cap = max(MAX_INCOMING_CONNECTIONS, 2 * max_robots + 64)
    return cap if fd_limit <= 0 else max(1, min(cap, fd_limit - FD_RESERVE))


def start_grpc_server(
    service: ArmoryService,
    host: str,
    port: int,
    max_robots: int,
    max_message_bytes: int,
    tls: tuple[bytes, bytes] | None = None,
    admin: ArmoryAdminServicer | None = None,
) -> RunningServer:
    """Bind and start the gRPC server (``port=0`` picks a free port; ``tls`` = (key, cert) PEM).

    Also raises the process's open-file limit (:func:`raise_fd_limit`) and bounds what a client
    that connects and sends nothing can hold: :data:`HANDSHAKE_TIMEOUT_MS`,
    :data:`MAX_CONNECTION_IDLE_MS`, :data:`MAX_INCOMING_CONNECTIONS`.
    """
    # Every connection, even one that never speaks, holds an fd until gRPC drops it.
    fd_limit = raise_fd_limit()
    # Each robot stream holds one worker thread for writing (its reader has its own thread).
    pool = futures.ThreadPoolExecutor(max_workers=max_robots + 8, thread_name_prefix="armory-grpc")
    server = grpc.server(
        pool,
        maximum_concurrent_rpcs=max_robots + 8,
        options=[
            ("grpc.max_receive_message_length", max_message_bytes),
            ("grpc.max_send_message_length", max_message_bytes),
            ("grpc.so_reuseport", 0),
            ("grpc.server_handshake_timeout_ms", HANDSHAKE_TIMEOUT_MS),
            ("grpc.max_connection_idle_ms", MAX_CONNECTION_IDLE_MS),
            *SERVER_KEEPALIVE_OPTIONS,
            ("grpc.max_allowed_incoming_connections", _connection_cap(max_robots, fd_limit)),
        ],
    )
    add_armory_to_server(service, server)
    if admin is not None:  # the operator's RPCs (entrypoints/grpc/admin.py), on the same port
        add_admin_to_server(admin, server)
    health_servicer = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    address = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    if tls is not None:
        bound = server.add_secure_port(address, grpc.ssl_server_credentials([tls]))
    else:
        bound = server.add_insecure_port(address)
    if bound == 0:
        raise ConfigError("port", f"cannot bind {address} (in use or not allowed)")
    server.start()
    running = RunningServer(server, bound, health_servicer)
    running.set_serving(True)
    return running


def shutdown_notice(fleet: Fleet, message: str = "the server is shutting down; reconnect later") -> Callable[[], None]:
    """Tell every connected robot the server stops, then close their streams."""

    def notify() -> None:
        with fleet.cond:
            for s in list(fleet.sessions.values()):
                s.outbox.put(Notice(NoticeKind.SHUTDOWN, message))
                s.outbox.close()

    return notify
