"""The robot's side of the wire: register, then one bidirectional stream. Small on purpose.

It knows nothing about control loops: it sends what it is given and calls back with what
arrives. :class:`~lerobot_armory.robot.client.ArmoryClient` builds the control loop on it; tests
and benchmarks use it directly as a robot double.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import grpc
import numpy as np

from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import ArmoryStub
from lerobot_armory.proto.limits import CLIENT_KEEPALIVE_OPTIONS, DEFAULT_MAX_MESSAGE_BYTES, SESSION_KEY, TOKEN_KEY
from lerobot_armory.robot.netem import NetworkEmulator
from lerobot_armory.wire import FeatureSpec, decode, encode, spec_from_proto

_CLOSE = object()


@dataclass
class ReceivedChunk:
    """A chunk as the robot sees it."""

    chunk_id: int
    i_start: int
    actions: np.ndarray  # (H, action_dim) float32
    server_send_time: float
    arrival_time: float  # robot clock
    obs_capture_time: float
    episode: int = 0  # the episode of the observation it was computed from


@dataclass
class Registration:
    """What the server answered at registration."""

    session_id: str
    action_names: list[str]
    chunk_size: int
    policy: str
    expected_features: list[FeatureSpec]
    clock_sync: pb.ClockSync
    action_dim: int = 0  # length of each action vector (0: a server that did not say)
    granted: pb.Grant | None = None  # what the grant rules granted (None: a server that did not say)
    stream_address: str = ""  # a cluster front's answer: the replica the stream goes to ("" : this server)

    @classmethod
    def from_response(cls, response: pb.RegisterResponse, clock_sync: pb.ClockSync) -> Registration:
        """Read the server's answer (``clock_sync`` is the registration round trip, completed by the robot)."""
        granted = None
        if response.HasField("granted"):
            granted = pb.Grant()
            granted.CopyFrom(response.granted)  # a copy: the registration need not keep the whole response alive
        return cls(
            response.session_id,
            list(response.action_names),
            response.chunk_size,
            response.policy,
            [spec_from_proto(f) for f in response.expected_features],
            clock_sync,
            response.action_dim or len(response.action_names),
            granted,
            response.stream_address,
        )


def open_channel(address: str, tls_ca: bytes | None = None, options: list[tuple[str, Any]] | None = None) -> grpc.Channel:
    """A channel to an armory server: TLS checked against ``tls_ca`` (PEM), or plaintext without it."""
    if tls_ca is not None:
        credentials = grpc.ssl_channel_credentials(root_certificates=tls_ca)
        return grpc.secure_channel(address, credentials, options=options or [])
    return grpc.insecure_channel(address, options=options or [])


class Connection:
    """One robot's connection to an armory server.

    Args:
        address: ``host:port``.
        clock: the robot's clock (seconds); never assumed synchronised with the server's.
        max_message_bytes: largest message sent or received.
        network: optional emulated network delays (benchmarks); None sends at once.
        tls_ca: PEM of the CA that signed the server's certificate (TLS); None: plaintext.
        token: auth token, sent at registration and on the stream.
    """

    def __init__(
        self,
        address: str,
        clock: Callable[[], float] = time.monotonic,
        max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
        network: NetworkEmulator | None = None,
        tls_ca: bytes | None = None,
        token: str = "",
    ) -> None:
        self.address = address
        self.clock = clock
        self.network = network
        self.token = token
        self._options = [
            ("grpc.max_receive_message_length", max_message_bytes),
            ("grpc.max_send_message_length", max_message_bytes),
            *CLIENT_KEEPALIVE_OPTIONS,
        ]
        self._tls_ca = tls_ca
        self.channel = self._open_channel(address)
        self.stub = ArmoryStub(self.channel)
        self.registration: Registration | None = None
        self._outgoing: queue.Queue = queue.Queue()
        self._call = None
        self._receiver: threading.Thread | None = None
        self.closed = threading.Event()
        self.error: grpc.RpcError | None = None

    def _open_channel(self, address: str) -> grpc.Channel:
        return open_channel(address, self._tls_ca, self._options)

    def wait_ready(self, timeout: float) -> bool:
        """True once the server's port accepts connections (within ``timeout`` seconds)."""
        try:
            grpc.channel_ready_future(self.channel).result(timeout=timeout)
            return True
        except grpc.FutureTimeoutError:
            return False

    def register(
        self,
        robot_id: str,
        features: Mapping[str, tuple[str, tuple[int, ...]]],
        fps: float,
        h_min: int,
        h_max: int,
        weight: float = 1.0,
        tier: str = "slow",
        task: str = "",
        timeout: float = 10.0,
        policy_name: str = "",
    ) -> Registration:
        """Register; raises ``grpc.RpcError`` (INVALID_ARGUMENT lists every mismatch).
        ``policy_name`` names the policy to be served by where the server serves several."""
        request = pb.RegisterRequest(
            robot_id=robot_id,
            task=task,
            fps=fps,
            h_min=h_min,
            h_max=h_max,
            weight=weight,
            tier=tier,
            features=[pb.TensorSpec(name=n, dtype=d, shape=list(s)) for n, (d, s) in features.items()],
            client_send_time=self.clock(),
            auth_token=self.token,
            policy_name=policy_name,
        )
        response = self.stub.Register(request, timeout=timeout)
        sync = pb.ClockSync(
            client_send_time=request.client_send_time,
            server_recv_time=response.server_recv_time,
            server_send_time=response.server_send_time,
            client_recv_time=self.clock(),
        )
        self.registration = Registration.from_response(response, sync)
        if response.stream_address and response.stream_address != self.address:
            # A cluster's front placed this robot on a replica: the session lives there, so the
            # stream (and everything after it) goes there, with the same TLS trust and limits.
            self.channel.close()
            self.address = response.stream_address
            self.channel = self._open_channel(self.address)
            self.stub = ArmoryStub(self.channel)
        return self.registration

    def open_stream(
        self,
        on_chunk: Callable[[ReceivedChunk], None],
        on_notice: Callable[[pb.Notice], None] | None = None,
        on_close: Callable[[grpc.RpcError | None], None] | None = None,
    ) -> None:
        """Open the stream; callbacks run on a receiver thread."""
        assert self.registration is not None, "register first"
        self._outgoing.put(pb.RobotMessage(clock_sync=self.registration.clock_sync))
        self._call = self.stub.Stream(self._requests(), metadata=self._stream_metadata())

        def receive() -> None:
            error = None
            try:
                for msg in self._call:
                    kind = msg.WhichOneof("kind")
                    if kind == "chunk":
                        c = msg.chunk
                        actions = decode(c.actions)

                        def deliver(c=c, actions=actions) -> None:  # arrival is when the robot sees it
                            on_chunk(
                                ReceivedChunk(c.chunk_id, c.i_start, actions, c.server_send_time, self.clock(), c.obs_capture_time, c.episode)
                            )

                        if self.network is None:
                            deliver()
                        else:
                            self.network.receive(deliver)
                    elif kind == "sync_request":
                        self._answer_sync(msg.sync_request)
                    elif kind == "notice" and on_notice is not None:
                        on_notice(msg.notice)
            except grpc.RpcError as exc:
                if exc.code() != grpc.StatusCode.CANCELLED:
                    error = exc
                    self.error = exc
            finally:
                self.closed.set()
                if on_close is not None:
                    on_close(error)

        self._receiver = threading.Thread(target=receive, name="armory-receive", daemon=True)
        self._receiver.start()

    def _answer_sync(self, request: pb.ClockSyncRequest) -> None:
        """Answer the server's clock-exchange request at once, through the same path as everything else.

        The request is "received" when the robot would see a chunk sent at the same moment (after
        the emulated downlink) and the answer is stamped when it enters the stream (after the
        emulated uplink): the exchange then measures the delays observations and chunks really see.
        """

        def arrived() -> None:
            recv = self.clock()
            self._enqueue(
                lambda: pb.RobotMessage(
                    clock_sync=pb.ClockSync(
                        sync_id=request.sync_id,
                        client_recv_time=recv,
                        client_send_time=self.clock(),
                        server_send_time=request.server_send_time,
                    )
                )
            )

        if self.network is None:
            arrived()
        else:
            self.network.receive(arrived)

    def _stream_metadata(self) -> tuple[tuple[str, str], ...]:
        assert self.registration is not None, "register first"
        metadata = [(SESSION_KEY, self.registration.session_id)]
        if self.token:
            metadata.append((TOKEN_KEY, self.token))
        return tuple(metadata)

    def end_session(self, timeout: float = 2.0) -> None:
        """Give a registration back unused (no stream was opened), then close.

        The protocol has no Unregister call: the server forgets a robot when its stream ends and
        keeps a registration that never streamed for its ``stale_session_s`` (a fleet slot and the
        robot id). Opening the stream with nothing to send and waiting for the server to end it
        frees both at once, without touching the wire format.
        """
        if self.registration is not None and self._call is None:
            try:
                for _ in self.stub.Stream(iter(()), metadata=self._stream_metadata(), timeout=timeout):
                    pass
            except grpc.RpcError:
                pass  # the server is gone or refused the stream: the registration expires there anyway
        self.close()

    def _requests(self) -> Iterator[pb.RobotMessage]:
        while True:
            item = self._outgoing.get()
            if item is _CLOSE:
                return
            yield item

    def send_observation(
        self,
        index: int,
        arrays: Mapping[str, np.ndarray],
        capture_time: float | None = None,
        jpeg_quality: int | None = None,
        episode: int = 0,
    ) -> None:
        """Queue one observation (images JPEG-encoded when ``jpeg_quality`` is set) of ``episode``."""
        tensors = []
        for name, arr in arrays.items():
            q = jpeg_quality if (jpeg_quality is not None and arr.dtype == np.uint8 and arr.ndim == 3) else None
            tensors.append(encode(name, arr, q))
        t = self.clock() if capture_time is None else capture_time
        self._enqueue(pb.RobotMessage(observation=pb.Observation(index=index, capture_time=t, tensors=tensors, episode=episode)))

    def _enqueue(self, msg: pb.RobotMessage | Callable[[], pb.RobotMessage]) -> None:
        """Send ``msg`` after the emulated uplink delay, if any.

        A callable is built only when the message enters the stream, so that send-time stamps in
        it (a clock sync's) are taken after the emulated delay, not before.
        """
        build = msg if callable(msg) else lambda: msg
        if self.network is None:
            self._outgoing.put(build())
        else:
            self.network.send(lambda: self._outgoing.put(build()))

    def send_raw(self, msg: pb.RobotMessage) -> None:
        """Queue any message (tests use it to send malformed ones)."""
        self._outgoing.put(msg)

    def send_report(
        self, index: int, executed: int, starved: int, receipts: list[tuple[int, float, int]], report_time: float | None = None
    ) -> None:
        """Queue an execution report; ``receipts`` are (chunk_id, arrival_time, first_executed_index or -1)."""
        self._enqueue(
            pb.RobotMessage(
                report=pb.ExecutionReport(
                    report_time=self.clock() if report_time is None else report_time,
                    index=index,
                    executed_steps=executed,
                    starved_steps=starved,
                    chunks=[pb.ChunkReceipt(chunk_id=c, arrival_time=a, first_executed_index=f) for c, a, f in receipts],
                )
            )
        )

    def close(self) -> None:
        """End the stream and the channel."""
        self._outgoing.put(_CLOSE)
        if self.network is not None:
            self.network.close()
        if self._call is not None:
            self._call.cancel()
        if self._receiver is not None:
            self._receiver.join(timeout=5)
        self.channel.close()
