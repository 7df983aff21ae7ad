"""Transport hardening ("one robot cannot hurt the fleet"): JPEG scan bombs, garbage protobuf,
per-peer log throttling, idle sockets and the connection cap."""

from __future__ import annotations

import io
import logging
import queue
import resource
import socket
import time

import numpy as np
import pytest
from PIL import Image

from lerobot_armory import wire
from tests.support.echo import echo_server
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.entrypoints.grpc.hardening import Malformed, add_armory_to_server, rpc_names, safe_deserializer
from lerobot_armory.robot.connection import Connection
from lerobot_armory.entrypoints.grpc import service
from lerobot_armory.serving.peer_log import ThrottledLog
from lerobot_armory.wire import MAX_JPEG_SCANS, WireError

FEATURES = {"observation.state": ("float32", (4,))}
STATE = {"observation.state": np.zeros(4, np.float32)}


# ---- JPEG decode cost ---------------------------------------------------------------------------


def jpeg(height: int = 48, width: int = 64, **save: object) -> bytes:
    """A PIL-encoded JPEG of a noisy image (``progressive=True`` for a progressive one)."""
    rng = np.random.default_rng(0)
    buf = io.BytesIO()
    Image.fromarray((rng.random((height, width, 3)) * 255).astype(np.uint8)).save(buf, "JPEG", **save)
    return buf.getvalue()


def with_repeated_last_scan(data: bytes, times: int) -> bytes:
    """``data`` (a progressive JPEG) with its last scan segment repeated ``times`` more times before EOI."""
    assert data.endswith(b"\xff\xd9")
    last = data.rfind(b"\xff\xda")  # entropy-coded data stuffs 0xFF as FF00: FFDA is always a marker
    return data[:-2] + data[last:-2] * times + b"\xff\xd9"


def jpeg_tensor(data: bytes, height: int = 48, width: int = 64) -> pb.Tensor:
    return pb.Tensor(name="cam", dtype="uint8", shape=[height, width, 3], data=data, encoding=pb.JPEG)


@pytest.mark.parametrize("save", [{}, {"progressive": True}, {"progressive": True, "optimize": True, "subsampling": 0}])
def test_pil_baseline_and_progressive_jpegs_decode(save):
    data = jpeg(**save)
    assert data.count(b"\xff\xda") == (10 if save else 1)  # libjpeg's progressive script has 10 scans
    array = wire.decode(jpeg_tensor(data))
    assert array.shape == (48, 64, 3) and array.dtype == np.uint8


def test_opencv_progressive_jpeg_with_restart_markers_decodes():
    cv2 = pytest.importorskip("cv2")
    image = np.random.default_rng(1).integers(0, 255, (48, 64, 3), np.uint8)
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1, cv2.IMWRITE_JPEG_RST_INTERVAL, 1])
    assert ok
    assert wire.decode(jpeg_tensor(data.tobytes())).shape == (48, 64, 3)


def test_jpeg_scan_count_limit_is_inclusive():
    base = jpeg(progressive=True)
    at_limit = with_repeated_last_scan(base, MAX_JPEG_SCANS - 10)
    assert wire.decode(jpeg_tensor(at_limit)).shape == (48, 64, 3)
    with pytest.raises(WireError, match=f"{MAX_JPEG_SCANS + 1} scans"):
        wire.decode(jpeg_tensor(with_repeated_last_scan(base, MAX_JPEG_SCANS - 9)))


def test_jpeg_scan_bomb_is_refused_without_decoding():
    # A black progressive image: its last scan is ~12 bytes, so 100k of them fit in ~1.2 MB, well under
    # the default 16 MB message limit; decoded, it costs ~0.3 s of CPU at this size and ~19 s at 640x480.
    buf = io.BytesIO()
    Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(buf, "JPEG", quality=90, progressive=True)
    bomb = with_repeated_last_scan(buf.getvalue(), 100_000)
    assert len(bomb) < 2 << 20
    start = time.perf_counter()
    with pytest.raises(WireError, match="100010 scans, more than the 64 allowed"):
        wire.decode(jpeg_tensor(bomb))
    assert time.perf_counter() - start < 0.1  # ~2 ms measured: counted, not decoded


def test_jpeg_with_two_frame_headers_is_refused():
    data = jpeg(progressive=True)
    sof = data[data.index(b"\xff\xc2") : data.index(b"\xff\xc4")]  # PIL writes SOF2 right before the first DHT
    with pytest.raises(WireError, match="more than one frame header"):
        wire.decode(jpeg_tensor(data[:2] + sof + data[2:]))


def test_jpeg_header_segment_flood_is_refused_fast():
    # PIL parses the header in Python one segment at a time: 4M empty comments cost it ~3.4 s.
    data = jpeg()
    flood = data[:2] + b"\xff\xfe\x00\x02" * 1_000_000 + data[2:]
    start = time.perf_counter()
    with pytest.raises(WireError, match="marker segments before its first scan"):
        wire.decode(jpeg_tensor(flood))
    assert time.perf_counter() - start < 0.1


@pytest.mark.parametrize(
    "mangle, message",
    [
        (lambda d: d[:2] + b"junk" + d[2:], "no marker at byte 2"),
        (lambda d: d[:2] + b"\xff" * 100 + d[2:], "no marker at byte 2"),
        (lambda d: d[:60], "bad segment length"),
        (lambda d: b"\xff\xd8\xff\xd9", "ends before its first scan"),
    ],
)
def test_malformed_jpeg_structure_is_refused(mangle, message):
    with pytest.raises(WireError, match=message):
        wire.decode(jpeg_tensor(mangle(jpeg())))


def test_non_jpeg_data_is_still_named():
    buf = io.BytesIO()
    Image.fromarray(np.zeros((48, 64, 3), np.uint8)).save(buf, "PNG")
    with pytest.raises(WireError, match="data is PNG"):
        wire.decode(jpeg_tensor(buf.getvalue()))


# ---- garbage protobuf -------------------------------------------------------------------------------


@pytest.mark.parametrize("message_type", [pb.RobotMessage, pb.RegisterRequest])
def test_safe_deserializer_turns_garbage_into_malformed(message_type):
    parse = safe_deserializer(message_type)
    garbage = parse(b"\xff\xff\xff\xff garbage")
    assert isinstance(garbage, Malformed)
    assert garbage.size == 12 and "DecodeError" in garbage.error
    assert parse(b"") == message_type()  # empty bytes are a valid (empty) message
    good = message_type()
    assert parse(good.SerializeToString()) == good


def test_safe_deserializer_catches_any_parser_exception():
    class Exploding:
        @staticmethod
        def FromString(data: bytes) -> None:
            raise RecursionError("nested too deep" * 100)

    result = safe_deserializer(Exploding)(b"abc")
    assert result == Malformed(result.error, 3)
    assert result.error.startswith("RecursionError: nested too deep") and len(result.error) <= 200


def test_every_served_method_parses_with_the_safe_deserializer():
    class Recorder:  # stands in for a grpc.Server: keeps the handlers it is given
        def __init__(self) -> None:
            self.handlers: dict = {}

        def add_generic_rpc_handlers(self, handlers) -> None:
            self.generic = handlers

        def add_registered_method_handlers(self, service_name, handlers) -> None:
            self.handlers = handlers

    class Servicer:
        def Register(self, request, context):
            return request

        def Stream(self, requests, context):
            return requests

    recorder = Recorder()
    add_armory_to_server(Servicer(), recorder)
    assert set(recorder.handlers) == set(rpc_names())
    for handler in recorder.handlers.values():
        assert isinstance(handler.request_deserializer(b"\xff\xff"), Malformed)


class FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_throttled_log_writes_one_line_per_peer_per_interval(caplog):
    clock = FakeClock()
    throttle = ThrottledLog(logging.getLogger("test.peers"), interval_s=10.0, clock=clock)
    with caplog.at_level(logging.WARNING, logger="test.peers"):
        assert throttle.warn("ipv4:10.0.0.1:5000", "malformed message ignored (12 bytes)")
        for _ in range(5):
            clock.now += 1.0
            assert not throttle.warn("ipv4:10.0.0.1:5000", "malformed message ignored (12 bytes)")
        assert throttle.warn("ipv4:10.0.0.2:6000", "another robot is not held back")
        clock.now += 5.0  # 10 s after the first line
        assert throttle.warn("ipv4:10.0.0.1:5000", "malformed message ignored (7 bytes)")
        clock.now += 10.0
        assert throttle.warn("ipv4:10.0.0.1:5000", "malformed message ignored (7 bytes)")
    lines = [r.getMessage() for r in caplog.records]
    assert lines == [
        "ipv4:10.0.0.1:5000: malformed message ignored (12 bytes)",
        "ipv4:10.0.0.2:6000: another robot is not held back",
        "ipv4:10.0.0.1:5000: malformed message ignored (7 bytes) (5 more suppressed)",
        "ipv4:10.0.0.1:5000: malformed message ignored (7 bytes)",
    ]
    assert all(r.levelno == logging.WARNING and r.exc_info is None for r in caplog.records)  # no tracebacks
    assert throttle.suppressed_total == 5


def test_throttled_log_memory_is_bounded():
    clock = FakeClock()
    throttle = ThrottledLog(
        logging.getLogger("test.peers.bounded"), interval_s=10.0, forget_s=60.0, max_peers=100, clock=clock
    )
    for k in range(1000):  # every reconnect is a new host:port
        throttle.warn(f"ipv4:10.0.0.1:{k}", "garbage")
    assert len(throttle) == 100
    assert throttle.warn("ipv4:10.0.0.1:0", "garbage")  # the oldest were dropped: it is new again
    clock.now += 30.0
    throttle.warn("ipv4:10.0.0.9:1", "garbage")
    clock.now += 31.0  # everyone but the last peer has been quiet for more than forget_s
    assert throttle.warn("ipv4:10.0.0.9:1", "garbage")
    assert len(throttle) == 1


def test_throttled_log_refuses_a_forget_time_shorter_than_the_interval():
    with pytest.raises(ValueError):
        ThrottledLog(interval_s=10.0, forget_s=5.0)


# ArmoryService answers a Malformed with a notice (one a second) and ThrottledLog.warn (one line per peer per 10 s)
def test_garbage_bytes_on_the_stream_are_answered_and_the_fleet_goes_on(caplog):
    server = echo_server()
    conn = Connection(server.address)
    other = Connection(server.address)
    try:
        reg = conn.register("garbage", FEATURES, fps=20, h_min=1, h_max=5)
        raw = conn.channel.stream_stream(
            f"/{service.SERVICE_NAME}/Stream",
            request_serializer=lambda b: b,
            response_deserializer=pb.ServerMessage.FromString,
        )
        outgoing: queue.Queue = queue.Queue()
        for _ in range(20):
            outgoing.put(b"\xff\xff\xff\xff garbage")
        call = raw(iter(outgoing.get, None), metadata=((service.SESSION_KEY, reg.session_id),))
        notices = []
        with caplog.at_level(logging.WARNING):
            for msg in call:
                if msg.WhichOneof("kind") == "notice":
                    notices.append(msg.notice.message)
                    if "malformed message ignored" in msg.notice.message:
                        break
            assert any("malformed message ignored (12 bytes)" in n for n in notices), notices
            # the stream is still open after the garbage: a real message on it is still served
            outgoing.put(pb.RobotMessage().SerializeToString())
            for msg in call:
                if msg.WhichOneof("kind") == "notice" and "empty message ignored" in msg.notice.message:
                    break
            # another robot registers and is served
            other.register("bystander", FEATURES, fps=20, h_min=1, h_max=5)
            chunks: queue.Queue = queue.Queue()
            other.open_stream(chunks.put)
            other.send_observation(0, STATE)
            assert chunks.get(timeout=10).i_start >= 0
        outgoing.put(None)
        call.cancel()
        texts = [r.getMessage() for r in caplog.records]
        assert not any("Exception deserializing request" in t for t in texts)
        assert not any(r.exc_info for r in caplog.records)  # no traceback per message
        assert sum("malformed" in t for t in texts) <= 1  # 20 bad messages, one throttled line
    finally:
        other.close()
        conn.close()
        server.stop(0.5)


# ---- idle sockets, connection cap -------------------------------------------------------------------

IDLE_SOCKETS = 1100


def closed_by_peer(sock: socket.socket) -> bool:
    """True if the server closed ``sock`` (EOF or reset); False if it is still open.

    What the server wrote first (its HTTP/2 SETTINGS, then a GOAWAY saying why it closes) is read and dropped.
    """
    sock.setblocking(False)
    try:
        while sock.recv(4096):
            pass
        return True
    except BlockingIOError:
        return False
    except OSError:
        return True


def open_idle(port: int, n: int) -> list[socket.socket]:
    """``n`` TCP connections to ``port`` that never send a byte."""
    return [socket.create_connection(("127.0.0.1", port), timeout=10) for _ in range(n)]


def wait_closed(socks: list[socket.socket], timeout: float) -> int:
    """How many of ``socks`` the server has closed once all are or ``timeout`` passes."""
    end = time.monotonic() + timeout
    pending = list(socks)
    while pending and time.monotonic() < end:
        pending = [s for s in pending if not closed_by_peer(s)]
        time.sleep(0.1)
    return len(socks) - len(pending)


def test_raise_fd_limit_lifts_the_soft_limit_to_the_hard_one():
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(256, hard), hard))
        now = service.raise_fd_limit()
        assert (
            resource.getrlimit(resource.RLIMIT_NOFILE)[0]
            == now
            == (hard if hard != resource.RLIM_INFINITY else 1 << 20)
        )
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, resource.getrlimit(resource.RLIMIT_NOFILE)[0]), hard))


def test_connection_cap_stays_below_the_fd_limit():
    assert service._connection_cap(64, 1 << 20) == service.MAX_INCOMING_CONNECTIONS
    assert service._connection_cap(64, 1024) == 1024 - service.FD_RESERVE
    assert service._connection_cap(5000, 1 << 20) == 2 * 5000 + 64  # a big fleet still fits
    assert service._connection_cap(64, -1) == service.MAX_INCOMING_CONNECTIONS


@pytest.mark.slow
def test_idle_sockets_do_not_block_registration_and_are_closed_after_the_handshake_timeout():
    hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    if hard != resource.RLIM_INFINITY and hard < 2 * IDLE_SOCKETS + 600:
        pytest.skip(f"the fd hard limit ({hard}) is too low for {IDLE_SOCKETS} idle sockets and their server ends")
    server = echo_server()  # raises this process's soft fd limit to the hard one
    socks = open_idle(server.port, IDLE_SOCKETS)
    conn = Connection(server.address)
    try:
        time.sleep(0.5)  # let the server accept them all
        start = time.monotonic()
        conn.register("r1", FEATURES, fps=20, h_min=1, h_max=5, timeout=10)
        assert time.monotonic() - start < 10  # ~0.01 s measured; ~60 s at a 1024 fd limit before
        assert not any(closed_by_peer(s) for s in socks[:100])  # still open: the timeout closes them, not the cap
        closed = wait_closed(socks, service.HANDSHAKE_TIMEOUT_MS / 1000 + 5)
        assert closed == IDLE_SOCKETS
        conn.register("r2", FEATURES, fps=20, h_min=1, h_max=5, timeout=10)  # the server still serves
    finally:
        for s in socks:
            s.close()
        conn.close()
        server.stop(0.5)


def test_connections_over_the_cap_are_closed_at_once(monkeypatch):
    monkeypatch.setattr(service, "MAX_INCOMING_CONNECTIONS", 16)
    server = echo_server(max_robots=2)  # cap: max(16, 2 * 2 + 64) = 68
    socks = open_idle(server.port, 100)
    try:
        # well before the handshake timeout, exactly the connections over the cap are gone
        time.sleep(1.0)
        closed = sum(closed_by_peer(s) for s in socks)
        assert closed == 100 - 68
    finally:
        for s in socks:
            s.close()
        server.stop(0.5)


def test_a_connection_holding_no_rpc_is_closed_after_the_idle_timeout(monkeypatch):
    monkeypatch.setattr(service, "MAX_CONNECTION_IDLE_MS", 500)
    server = echo_server()
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=10)
    try:
        # a client preface and an empty SETTINGS frame: past the handshake timeout, but no RPC ever
        sock.sendall(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + b"\x00\x00\x00\x04\x00\x00\x00\x00\x00")
        start = time.monotonic()
        assert wait_closed([sock], 5.0) == 1
        assert 0.3 < time.monotonic() - start < 3.0
    finally:
        sock.close()
        server.stop(0.5)


@pytest.mark.slow
def test_a_quiet_stream_outlives_the_idle_connection_timeout(monkeypatch):
    monkeypatch.setattr(service, "MAX_CONNECTION_IDLE_MS", 500)
    server = echo_server()
    conn = Connection(server.address)
    try:
        conn.register("quiet", FEATURES, fps=20, h_min=1, h_max=5)
        chunks: queue.Queue = queue.Queue()
        conn.open_stream(chunks.put)
        time.sleep(2.0)  # four idle timeouts with the stream open and nothing sent
        assert not conn.closed.is_set()
        conn.send_observation(0, STATE)
        assert chunks.get(timeout=10).i_start >= 0
    finally:
        conn.close()
        server.stop(0.5)
    # a channel whose connection was closed for idleness reconnects by itself
    server = echo_server()
    conn = Connection(server.address)
    try:
        conn.register("idle-1", FEATURES, fps=20, h_min=1, h_max=5)
        time.sleep(1.5)
        conn.register("idle-2", FEATURES, fps=20, h_min=1, h_max=5)
    finally:
        conn.close()
        server.stop(0.5)
