"""Hostile and broken robots against a live armory server, one function per attack.

Every scenario is ``name(address, stop, features, report=None, **options) -> AttackReport``. It
runs in the caller's thread until ``stop`` is set (the benchmark and the tests start it on a
thread of their own), speaks the real protocol over a :class:`Connection`'s channel, sends what
no honest client would (raw messages, or raw bytes), and keeps at it the way a broken or hostile
robot would: a stream the server drops is registered and opened again. What the server answered
goes into an :class:`AttackReport`: registration and stream status codes, notices, chunks,
dropped streams, and *violations*: answers that break a rule the attacker can check by itself
(a fleet token that registered a robot id holding its own token, a registration with an absurd
rate granted as asked). ``features`` is ``{name: (dtype, shape)}`` of what the server expects
(zeros are sent).

Scenarios: clock_nan, capture_absurd, report_absurd, fps_absurd, priority_flood, clock_ahead,
huge_report, never_reads, slot_squat, identity, idle_sockets, garbage, openpi_idle, openpi_garbage,
openpi_never_reads (``SCENARIOS``; honest stand-ins in ``STANDINS``). The 11th
attack of the benchmark, a robot whose clock steps, is not an attacker but an honest robot with
a stepped clock: :func:`run_ticks` with a :class:`SteppedClock`.

The module is also the honest fleet's process for the benchmark:
``python tests/support/adversaries.py honest SPEC.json`` runs ``armory_sim`` robots built exactly as
``lerobot_armory.bench.robots.run_robot`` builds them (real ArmoryClient, ArmorySim, emulated
network), plus what the adversarial benchmark needs: an auth token per robot, a clock that steps
mid-run, and each robot's tick-by-tick timeline (so starvation can be measured over any window)
and time to its first chunk. Ticks start when the group starts, connected or not: a robot kept
out of the server starves, as a real one would.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import math
import queue
import random
import re
import resource
import socket
import struct
import sys
import functools
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import numpy as np

from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.robot.connection import Connection
from lerobot_armory.wire import encode

Features = Mapping[str, tuple[str, tuple[int, ...]]]

SESSION_KEY = "armory-session"
TOKEN_KEY = "armory-token"
STREAM_METHOD = "/lerobot_armory.v1.Armory/Stream"
CLOCK_FIELDS = ("client_send_time", "server_recv_time", "server_send_time", "client_recv_time")
NON_FINITE_OR_HUGE = (math.nan, math.inf, -math.inf, 1e308, -1e308)
INT64_MAX, INT64_MIN = 2**63 - 1, -(2**63)
MIB = 1 << 20

# What the harness calls a sane grant (the server's grant rules may be stricter): fps in
# [0.01, 1000] Hz, weight in (0, 1e6], 0 <= h_min <= h_max <= H. An accepted registration outside
# these is a violation; a refusal must be INVALID_ARGUMENT.
SANE_FPS = (0.01, 1000.0)
SANE_WEIGHT = (0.0, 1e6)


# ---- what the attacker saw -----------------------------------------------------------------------


@dataclass
class AttackReport:
    """Counts of what one attacker sent and what the server answered (thread-safe)."""

    scenario: str
    counts: Counter = field(default_factory=Counter)
    codes: Counter = field(default_factory=Counter)  # "register OK", "register INVALID_ARGUMENT", "stream INTERNAL"
    notices: Counter = field(default_factory=Counter)  # notice kind names
    violations: Counter = field(default_factory=Counter)  # a rule the server broke -> times
    events: list[str] = field(default_factory=list)  # notable things, first few
    extra: dict[str, Any] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def add(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.counts[key] += n

    def code(self, what: str, code: str) -> None:
        with self._lock:
            self.codes[f"{what} {code}"] += 1

    def notice(self, kind: str, message: str = "") -> None:
        with self._lock:
            self.notices[kind] += 1
            if message:  # a few distinct texts, numbers folded, for the report
                samples = self.extra.setdefault("notice samples", {})
                text = f"{kind}: " + re.sub(r"\d+(\.\d+)?(e[+-]?\d+)?", "N", message[:160])
                if text in samples or len(samples) < 8:
                    samples[text] = samples.get(text, 0) + 1

    def violation(self, text: str) -> None:
        with self._lock:
            self.violations[text] += 1

    def event(self, text: str) -> None:
        with self._lock:
            if len(self.events) < 40 and text not in self.events:
                self.events.append(text)

    def summary(self) -> str:
        """One line: what was sent and how the server answered."""
        parts = [f"{k}={v}" for k, v in sorted(self.counts.items()) if k != "bytes"]
        if self.counts.get("bytes"):
            parts.append(f"sent {self.counts['bytes'] / MIB:.1f} MiB")
        parts += [f"{k}={v}" for k, v in sorted(self.codes.items())]
        if self.notices:
            parts.append("notices " + ",".join(f"{k}={v}" for k, v in sorted(self.notices.items())))
        return "; ".join(parts)

    def to_json(self) -> dict[str, Any]:
        with self._lock:
            return {
                "scenario": self.scenario,
                "counts": dict(self.counts),
                "codes": dict(self.codes),
                "notices": dict(self.notices),
                "violations": dict(self.violations),
                "events": list(self.events),
                "extra": dict(self.extra),
            }


# ---- raw protocol pieces ------------------------------------------------------------------------


def _identity(b: bytes) -> bytes:
    return b


def _code_name(exc: grpc.RpcError) -> str:
    try:
        return exc.code().name
    except Exception:  # noqa: BLE001 - a non-call RpcError
        return "UNKNOWN"


class RawStream:
    """One session's bidirectional stream, bytes in and out: anything can be sent.

    ``read=False`` never reads what the server sends (the never-reading robot). ``on_message`` is
    called on the receiver thread with every decoded :class:`pb.ServerMessage`.
    """

    def __init__(
        self,
        channel: grpc.Channel,
        session_id: str,
        report: AttackReport,
        token: str = "",
        read: bool = True,
        on_message: Callable[[pb.ServerMessage], None] | None = None,
        max_queue: int = 64,
    ) -> None:
        self.report = report
        self.max_queue = max_queue
        self._q: queue.Queue = queue.Queue()
        self.closed = threading.Event()
        self.code: str | None = None
        self.details = ""
        metadata = [(SESSION_KEY, session_id)]
        if token:
            metadata.append((TOKEN_KEY, token))
        method = channel.stream_stream(STREAM_METHOD, request_serializer=_identity, response_deserializer=_identity)
        self.call = method(self._requests(), metadata=tuple(metadata))
        self.call.add_done_callback(self._done)
        self.on_message = on_message
        report.add("streams opened")
        if read:
            threading.Thread(target=self._receive, name="adversary-receive", daemon=True).start()

    def _requests(self) -> Iterator[bytes]:
        while True:
            item = self._q.get()
            if item is None:
                return
            yield item

    def _done(self, call: Any) -> None:
        with contextlib.suppress(Exception):  # a call that never started has no status
            code = call.code()
            self.code = code.name if code is not None else None
            self.details = call.details() or ""
        self.closed.set()

    def _receive(self) -> None:
        try:
            for raw in self.call:
                try:
                    msg = pb.ServerMessage.FromString(raw)
                except Exception:  # noqa: BLE001 - the server sent something we cannot parse
                    self.report.add("undecodable replies")
                    continue
                kind = msg.WhichOneof("kind")
                if kind == "chunk":
                    self.report.add("chunks")
                elif kind == "notice":
                    known = msg.notice.kind in pb.Notice.Kind.values()
                    self.report.notice(pb.Notice.Kind.Name(msg.notice.kind) if known else str(msg.notice.kind), msg.notice.message)
                elif kind is not None:
                    self.report.add(kind)
                if self.on_message is not None:
                    self.on_message(msg)
        except grpc.RpcError as exc:
            if exc.code() != grpc.StatusCode.CANCELLED:
                self.report.code("stream", _code_name(exc))
                self.report.event(f"stream ended {_code_name(exc)}: {(exc.details() or '')[:200]}")
        finally:
            self.closed.set()

    def send(self, msg: pb.RobotMessage | bytes, wait_s: float = 1.0) -> bool:
        """Queue one message (a protobuf or raw bytes); False if the stream is closed or stuck."""
        data = msg if isinstance(msg, bytes) else msg.SerializeToString()
        deadline = time.monotonic() + wait_s
        while self._q.qsize() > self.max_queue:  # the transport is not taking our messages
            if self.closed.is_set() or time.monotonic() > deadline:
                self.report.add("messages not sent (stream stuck)")
                return False
            time.sleep(0.002)
        if self.closed.is_set():
            return False
        self._q.put(data)
        self.report.add("messages")
        self.report.add("bytes", len(data))
        return True

    @property
    def alive(self) -> bool:
        return not self.closed.is_set()

    def close(self) -> None:
        self._q.put(None)
        self.call.cancel()


class Robot:
    """An attacking robot: a :class:`Connection`'s channel and stub, raw registrations, raw streams."""

    def __init__(
        self,
        address: str,
        features: Features,
        report: AttackReport,
        robot_id: str,
        fps: float = 20.0,
        h_min: int = 10,
        h_max: int = 10,
        weight: float = 1.0,
        tier: str = "slow",
        token: str = "",
        max_message_bytes: int = 16 * MIB,
    ) -> None:
        self.features = dict(features)
        self.report = report
        self.fields = {"robot_id": robot_id, "fps": fps, "h_min": h_min, "h_max": h_max, "weight": weight, "tier": tier}
        self.token = token
        self.conn = Connection(address, max_message_bytes=max_message_bytes, token=token)
        self.response: pb.RegisterResponse | None = None
        self.sync: pb.ClockSync | None = None
        self.error: grpc.RpcError | None = None
        self.stream: RawStream | None = None

    def request(self, **overrides: Any) -> pb.RegisterRequest:
        f = {**self.fields, **overrides}
        return pb.RegisterRequest(
            robot_id=f["robot_id"], fps=f["fps"], h_min=f["h_min"], h_max=f["h_max"], weight=f["weight"], tier=f["tier"],
            features=[pb.TensorSpec(name=n, dtype=d, shape=list(s)) for n, (d, s) in self.features.items()],
            client_send_time=time.monotonic(), auth_token=overrides.get("auth_token", self.token),
        )  # fmt: skip

    def register(self, timeout: float = 5.0, **overrides: Any) -> pb.RegisterResponse | None:
        """Register (``overrides`` replace request fields); None if refused (the code is recorded)."""
        request = self.request(**overrides)
        try:
            response = self.conn.stub.Register(request, timeout=timeout)
        except grpc.RpcError as exc:
            self.error = exc
            self.report.code("register", _code_name(exc))
            return None
        self.report.code("register", "OK")
        self.response = response
        self.sync = pb.ClockSync(
            client_send_time=request.client_send_time,
            server_recv_time=response.server_recv_time,
            server_send_time=response.server_send_time,
            client_recv_time=time.monotonic(),
        )
        return response

    def open(
        self, read: bool = True, on_message: Callable[[pb.ServerMessage], None] | None = None, sync: bool = True, token: str | None = None
    ) -> RawStream:
        """Open the registered session's stream (first message: the registration clock sync)."""
        assert self.response is not None, "register first"
        stream = RawStream(self.conn.channel, self.response.session_id, self.report, self.token if token is None else token, read, on_message)
        if sync and self.sync is not None:
            stream.send(pb.RobotMessage(clock_sync=self.sync))
        self.stream = stream
        return stream

    def connect(
        self,
        stop: threading.Event,
        read: bool = True,
        on_message: Callable[[pb.ServerMessage], None] | None = None,
        sync: bool = True,
        retry_s: float = 0.3,
        **overrides: Any,
    ) -> RawStream | None:
        """Register and open, again and again until it works or ``stop`` (None then)."""
        if self.stream is not None:
            if self.stream.alive:
                return self.stream
            self.report.add("streams ended by the server")
            if self.stream.code:
                self.report.event(f"stream ended by the server: {self.stream.code} {self.stream.details[:200]}")
            self.stream.close()
            self.stream = None
        while not stop.is_set():
            if self.register(**overrides) is not None:
                return self.open(read, on_message, sync)
            if self.error is not None and self.error.code() == grpc.StatusCode.UNAVAILABLE:
                self.report.event("server unreachable")
            stop.wait(retry_s)
        return None

    def close(self) -> None:
        if self.stream is not None:
            self.stream.close()
        self.conn.close()


class Observations:
    """Observations of zeros for the registered features (tensors encoded once)."""

    def __init__(self, features: Features) -> None:
        self.tensors = [encode(name, np.zeros(shape, dtype=dtype)) for name, (dtype, shape) in features.items()]

    def __call__(self, index: int, capture_time: float, tensors: list[pb.Tensor] | None = None) -> pb.RobotMessage:
        return pb.RobotMessage(observation=pb.Observation(index=index, capture_time=capture_time, tensors=tensors or self.tensors))


def ticks(rate_hz: float, stop: threading.Event) -> Iterator[int]:
    """0, 1, 2, ... at ``rate_hz`` until ``stop`` (no bursts to catch up)."""
    period = 1.0 / rate_hz
    k, next_t = 0, time.monotonic()
    while not stop.is_set():
        yield k
        k += 1
        next_t += period
        delay = next_t - time.monotonic()
        if delay > 0:
            stop.wait(delay)
        else:
            next_t = time.monotonic()


def flip_bits(value: float, rng: random.Random, n: int) -> float:
    """``value`` with ``n`` random bits of its IEEE-754 double flipped (NaN, inf, huge, tiny...)."""
    bits = struct.unpack("<Q", struct.pack("<d", value))[0]
    for _ in range(n):
        bits ^= 1 << rng.randrange(64)
    return struct.unpack("<d", struct.pack("<Q", bits))[0]


def _image_feature(features: Features) -> tuple[str, tuple[int, ...]] | None:
    for name, (dtype, shape) in features.items():
        if dtype == "uint8" and len(shape) == 3 and shape[2] == 3:
            return name, tuple(shape)
    return None


# ---- 1. clock_nan ------------------------------------------------------------------------------


def clock_nan(
    address: str, stop: threading.Event, features: Features, report: AttackReport | None = None, *, rate_hz: float = 20.0, token: str = ""
) -> AttackReport:
    """A robot whose clock exchanges carry NaN, +-inf and +-1e308 in each field in turn (every
    other tick), while it streams ordinary observations (index + 1 per tick) so that its mirror
    is in every scheduling decision."""
    report = report or AttackReport("clock_nan")
    robot = Robot(address, features, report, "atk-clock-nan", token=token)
    obs = Observations(features)
    combos = [(f, v) for v in NON_FINITE_OR_HUGE for f in CLOCK_FIELDS]
    index = 0
    for k in ticks(rate_hz, stop):
        stream = robot.connect(stop)
        if stream is None:
            break
        now = time.monotonic()
        stream.send(obs(index, now))
        index += 1
        if k % 2 == 0:
            name, value = combos[(k // 2) % len(combos)]
            sync = pb.ClockSync(client_send_time=now, server_recv_time=now, server_send_time=now, client_recv_time=now)
            setattr(sync, name, value)
            stream.send(pb.RobotMessage(clock_sync=sync))
            report.add("poisoned clock syncs")
    robot.close()
    return report


# ---- 2. capture_absurd ---------------------------------------------------------------------------

ABSURD_CAPTURES = (1e308, -1e308, 1e300, -1e300, 1.7976931348623157e308, 1e18, -1e18, -1.0, 0.0, 5e-324, -5e-324, 2.0**63)


def capture_absurd(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    rate_hz: float = 20.0,
    seed: int = 0,
    token: str = "",
) -> AttackReport:
    """Observations (index + 1 per tick) whose capture time is, every other tick, absurd: +-1e308,
    huge, negative, subnormal, or the true time with 1-3 random bits of the double flipped."""
    report = report or AttackReport("capture_absurd")
    rng = random.Random(seed)
    robot = Robot(address, features, report, "atk-capture", token=token)
    obs = Observations(features)
    index = 0
    for k in ticks(rate_hz, stop):
        stream = robot.connect(stop)
        if stream is None:
            break
        t = time.monotonic()
        if k % 2:
            t = ABSURD_CAPTURES[(k // 4) % len(ABSURD_CAPTURES)] if (k // 2) % 2 == 0 else flip_bits(t, rng, rng.randint(1, 3))
            report.add("absurd captures")
        stream.send(obs(index, t))
        index += 1
    robot.close()
    return report


# ---- 3. report_absurd ----------------------------------------------------------------------------

ABSURD_ARRIVALS = (1e308, -1e308, 1e300, -1e300, 1e18, -1e18, 5e-324, 0.0, -1.0, 1.7976931348623157e308)
ABSURD_INTS = (INT64_MAX, 2**62, 10**15, 0, -1, INT64_MIN)


def report_absurd(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    rate_hz: float = 20.0,
    seed: int = 0,
    h_min: int = 10,
    token: str = "",
) -> AttackReport:
    """An ordinary stream of observations, and every tick an execution report with absurd values
    for the chunks it really received: arrival times of +-1e308, huge, negative; report times of
    +-1e308; huge or negative counts; a huge index; receipts for chunk ids it never got.
    ``h_min`` 1 gets it a chunk (a receipt to poison) every tick or so; 10 every half second."""
    report = report or AttackReport("report_absurd")
    rng = random.Random(seed)
    received: list[int] = []
    lock = threading.Lock()

    def on_message(msg: pb.ServerMessage) -> None:
        if msg.WhichOneof("kind") == "chunk":
            with lock:
                received.append(msg.chunk.chunk_id)

    robot = Robot(address, features, report, "atk-report", h_min=h_min, token=token)
    obs = Observations(features)
    index = 0
    for _ in ticks(rate_hz, stop):
        stream = robot.connect(stop, on_message=on_message)
        if stream is None:
            break
        now = time.monotonic()
        stream.send(obs(index, now))
        index += 1
        with lock:
            fresh, received[:] = list(received), []
        ids = fresh + [rng.choice((INT64_MAX, -1, 0, rng.randrange(1000)))]
        receipts = [
            pb.ChunkReceipt(
                chunk_id=cid,
                arrival_time=rng.choice(ABSURD_ARRIVALS) if rng.random() < 0.8 else flip_bits(now, rng, 2),
                first_executed_index=rng.choice(ABSURD_INTS),
            )
            for cid in ids
        ]
        counts = [rng.choice(ABSURD_INTS[:4]) if rng.random() < 0.8 else rng.choice(ABSURD_INTS) for _ in range(2)]
        msg = pb.ExecutionReport(
            report_time=now if rng.random() < 0.5 else rng.choice((1e308, -1e308, 1e18, -1.0, 5e-324)),
            index=rng.choice(ABSURD_INTS),
            executed_steps=counts[0],
            starved_steps=counts[1],
            chunks=receipts,
        )
        stream.send(pb.RobotMessage(report=msg))
        report.add("absurd reports")
        report.add("receipts for received chunks", len(fresh))
    robot.close()
    return report


# ---- 4. fps_absurd -------------------------------------------------------------------------------

ABSURD_REGISTRATIONS: tuple[tuple[str, dict[str, Any]], ...] = (
    ("fps=1e308", {"fps": 1e308}),
    ("fps=1e-308", {"fps": 1e-308}),
    ("fps=5e-324", {"fps": 5e-324}),
    ("fps=nan", {"fps": math.nan}),
    ("fps=inf", {"fps": math.inf}),
    ("fps=-inf", {"fps": -math.inf}),
    ("fps=0", {"fps": 0.0}),
    ("fps=-20", {"fps": -20.0}),
    ("fps=1e9", {"fps": 1e9}),
    ("weight=1e308", {"weight": 1e308}),
    ("weight=1e-308", {"weight": 1e-308}),
    ("weight=nan", {"weight": math.nan}),
    ("weight=inf", {"weight": math.inf}),
    ("weight=-1", {"weight": -1.0}),
    ("h_min=-2^31", {"h_min": -(2**31)}),
    ("h_max=2^31-1", {"h_max": 2**31 - 1}),
    ("h_min=h_max=2^31-1", {"h_min": 2**31 - 1, "h_max": 2**31 - 1}),
    ("h_min=11>h_max=10", {"h_min": 11, "h_max": 10}),
    ("h_min=h_max=0", {"h_min": 0, "h_max": 0}),
    ("h_max=-1", {"h_max": -1}),
)


def _granted(response: pb.RegisterResponse, asked: dict[str, Any]) -> dict[str, Any]:
    """What the server will use: its Grant where it sends one, else what was asked."""
    if "granted" in pb.RegisterResponse.DESCRIPTOR.fields_by_name and response.HasField("granted"):
        g = response.granted
        return {"fps": g.fps, "weight": g.weight, "h_min": g.h_min, "h_max": g.h_max, "grant": True}
    return {**asked, "grant": False}


def check_grant(label: str, response: pb.RegisterResponse, asked: dict[str, Any], report: AttackReport) -> None:
    """A violation if an accepted registration runs with values outside the harness's sane bounds."""
    eff = _granted(response, asked)
    H = response.chunk_size
    problems = []
    if not (math.isfinite(eff["fps"]) and SANE_FPS[0] <= eff["fps"] <= SANE_FPS[1]):
        problems.append(f"fps={eff['fps']:g}")
    if not (math.isfinite(eff["weight"]) and SANE_WEIGHT[0] < eff["weight"] <= SANE_WEIGHT[1]):
        problems.append(f"weight={eff['weight']:g}")
    if not (0 <= eff["h_min"] <= eff["h_max"] and 1 <= eff["h_max"] <= max(H, 1)):
        problems.append(f"h=[{eff['h_min']},{eff['h_max']}]")
    if problems:
        how = "granted" if eff["grant"] else "accepted (no grant in the answer)"
        report.violation(f"registration {label} {how} as {', '.join(problems)}")


def fps_absurd(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    rate_hz: float = 20.0,
    token: str = "",
    registrations: tuple[tuple[str, dict[str, Any]], ...] = ABSURD_REGISTRATIONS,
) -> AttackReport:
    """Registrations with absurd fps, weight and horizons; each must be refused with
    INVALID_ARGUMENT or granted inside sane bounds (else a violation). Every accepted one then
    streams observations (index + 1 per tick), re-registering when dropped."""
    report = report or AttackReport("fps_absurd")
    base = {"fps": 20.0, "h_min": 10, "h_max": 10, "weight": 1.0}
    accepted: list[tuple[str, Robot, dict[str, Any]]] = []
    for k, (label, overrides) in enumerate(registrations):
        if stop.is_set():
            break
        asked = {**base, **overrides}
        robot = Robot(address, features, report, f"atk-fps-{k}", token=token, **asked)
        response = robot.register()
        if response is None:
            code = _code_name(robot.error) if robot.error is not None else "?"
            report.extra.setdefault("outcomes", {})[label] = code
            if code != "INVALID_ARGUMENT":
                report.violation(f"registration {label} answered {code} (expected INVALID_ARGUMENT or a bounded grant)")
            robot.close()
            continue
        report.extra.setdefault("outcomes", {})[label] = "accepted " + json.dumps({k: v for k, v in _granted(response, asked).items() if k != "grant"}, default=str)
        check_grant(label, response, asked, report)
        robot.open()
        accepted.append((label, robot, asked))
    obs = Observations(features)
    index = 0
    for _ in ticks(rate_hz, stop):
        now = time.monotonic()
        for _label, robot, _asked in accepted:
            stream = robot.connect(stop, retry_s=1.0)
            if stream is not None:
                stream.send(obs(index, now))
        index += 1
    for _, robot, _ in accepted:
        robot.close()
    return report


# ---- 5. priority_flood ---------------------------------------------------------------------------


def priority_flood(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    rate_hz: float = 190.0,
    weight: float = 3.0,
    token: str = "",
) -> AttackReport:
    """Asks for weight 3 and h_min 0 at a declared 20 fps, then claims to execute 190 steps a
    second: observations at 190 Hz (under the default 200 obs/s limit), index + 1 each."""
    report = report or AttackReport("priority_flood")
    robot = Robot(address, features, report, "atk-priority", fps=20.0, h_min=0, h_max=10, weight=weight, tier="fast", token=token)
    obs = Observations(features)
    index = 0
    for _ in ticks(rate_hz, stop):
        stream = robot.connect(stop)
        if stream is None:
            break
        if "granted weight" not in report.extra and robot.response is not None:
            report.extra["granted weight"] = _granted(robot.response, {"weight": weight, "fps": 20.0, "h_min": 0, "h_max": 10})["weight"]
        stream.send(obs(index, time.monotonic()))
        index += 1
    robot.close()
    return report


# ---- 6. clock_ahead ------------------------------------------------------------------------------


def clock_ahead(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    lie_s: float = 1e6,
    rate_hz: float = 20.0,
    token: str = "",
) -> AttackReport:
    """Its clock exchanges claim its clock reads ``lie_s`` seconds ahead of the clock it stamps
    observations with, so the server's offset estimate is off by ``lie_s``: with lie_s > 0 every
    observation looks ``lie_s`` seconds old and the robot long run dry (the most urgent robot an
    EDF server ever saw). Otherwise honest-looking: 20 Hz, index + 1 per tick, h_min 1. It
    answers the server's ClockSyncRequests with the same lie."""
    report = report or AttackReport("clock_ahead")
    holder: dict[str, RawStream | None] = {"stream": None}

    def on_message(msg: pb.ServerMessage) -> None:
        if msg.WhichOneof("kind") == "sync_request":
            now = time.monotonic() + lie_s
            answer = pb.ClockSync(client_recv_time=now, client_send_time=now, server_send_time=msg.sync_request.server_send_time)
            if "sync_id" in pb.ClockSync.DESCRIPTOR.fields_by_name:
                answer.sync_id = msg.sync_request.sync_id
            stream = holder["stream"]
            if stream is not None:
                stream.send(pb.RobotMessage(clock_sync=answer))
                report.add("lying answers to sync requests")

    robot = Robot(address, features, report, "atk-clock-ahead", h_min=1, h_max=10, token=token)
    obs = Observations(features)
    index = 0
    for _ in ticks(rate_hz, stop):
        stream = robot.stream
        if stream is None or not stream.alive:
            stream = robot.connect(stop, on_message=on_message, sync=False)
            if stream is None:
                break
            holder["stream"] = stream
            assert robot.sync is not None
            lie = pb.ClockSync()
            lie.CopyFrom(robot.sync)
            lie.client_send_time += lie_s
            lie.client_recv_time += lie_s
            stream.send(pb.RobotMessage(clock_sync=lie))
        stream.send(obs(index, time.monotonic()))
        index += 1
    robot.close()
    return report


# ---- 6b. share_liar ------------------------------------------------------------------------------


def share_liar(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    rate_hz: float = 190.0,
    fps: float = 20.0,
    h_min: int = 0,
    h_max: int = 10,
    token: str = "",
    honest: bool = False,
    robot_id: str = "atk-share",
    lean_twin: bool = False,
) -> AttackReport:
    """Tries to buy service with lies the server cannot see directly: registers ``fps`` and
    ``h_min`` like a robot that may be served at once, then sends ``rate_hz`` observations a
    second (under the server's 200/s), each stamped now and claiming it has executed everything
    it received (the index at the end of its newest chunk), and reports every chunk's arrival
    truthfully so its delay estimate stays good. It executes nothing. ``report.extra`` gets its
    chunks per second from its first chunk to the end (``chunks/s``), to compare with an honest
    robot of the same registration.

    ``honest=True`` is the control (``share_lean``): the same lean client, the same 190
    observations a second stamped now, but claiming only what it really executed: one action
    per tick of its own ``fps`` clock, when a chunk that had arrived by that tick covers it. The
    liar and this robot differ only by the lie, where the armory_sim twin also differs by its
    client (images rendered, a control loop that sees a chunk at its next tick).

    ``lean_twin=True`` runs that honest control beside the liar, in the same run, as robot
    ``lean-twin``: its chunks per second go to ``report.extra["lean chunks/s"]``."""
    report = report or AttackReport("share_lean" if honest else "share_liar")
    twin_thread = None
    if lean_twin:
        twin_report = AttackReport("share_lean")
        twin_kwargs = {"rate_hz": rate_hz, "fps": fps, "h_min": h_min, "h_max": h_max, "token": token}
        twin_thread = threading.Thread(
            target=share_liar, args=(address, stop, features, twin_report),
            kwargs={**twin_kwargs, "honest": True, "robot_id": "lean-twin"}, name="lean-twin", daemon=True,
        )  # fmt: skip
        twin_thread.start()
    lock = threading.Lock()
    state = {"end": 0, "first": None, "last": None, "n": 0}
    arrivals: list[tuple[int, float]] = []
    held: list[tuple[int, float]] = []  # (i_start, arrival) of every chunk received (honest)

    def on_message(msg: pb.ServerMessage) -> None:
        if msg.WhichOneof("kind") != "chunk":
            return
        now = time.monotonic()
        with lock:
            state["end"] = max(state["end"], msg.chunk.i_start + h_max)
            state["first"] = state["first"] if state["first"] is not None else now
            state["last"], state["n"] = now, state["n"] + 1
            arrivals.append((msg.chunk.chunk_id, now))
            held.append((msg.chunk.i_start, now))

    robot = Robot(address, features, report, robot_id, fps=fps, h_min=h_min, h_max=h_max, token=token)
    obs = Observations(features)
    index = 0
    start = time.monotonic()
    next_tick = start  # the honest control's execution clock
    for k in ticks(rate_hz, stop):
        stream = robot.connect(stop, on_message=on_message)
        if stream is None:
            break
        now = time.monotonic()
        with lock:
            if honest:
                while next_tick <= now:  # each tick since the last loop executes one action if it can
                    if any(s <= index < s + h_max and t <= next_tick for s, t in held):
                        index += 1
                    next_tick += 1.0 / fps
                held[:] = [(s, t) for s, t in held if s + h_max > index]
            else:
                index = max(index, state["end"])
            fresh, arrivals[:] = list(arrivals), []
        stream.send(obs(index, now))
        if fresh or k % 20 == 0:
            receipts = [pb.ChunkReceipt(chunk_id=cid, arrival_time=t, first_executed_index=0) for cid, t in fresh]
            stream.send(pb.RobotMessage(report=pb.ExecutionReport(report_time=now, index=index, executed_steps=index, chunks=receipts)))
    robot.close()
    end = time.monotonic()
    with lock:
        report.extra["chunks"] = state["n"]
        report.extra["chunks/s"] = state["n"] / max(1e-9, end - start)
        report.extra["claimed index"] = index
    if twin_thread is not None:
        twin_thread.join(timeout=30)
        report.extra["lean chunks/s"] = twin_report.extra.get("chunks/s")
    return report


# ---- 7. huge_report ------------------------------------------------------------------------------


def huge_report_bytes(max_message_bytes: int, margin: int = 1024) -> tuple[bytes, int]:
    """A serialized ``RobotMessage(report=...)`` just under ``max_message_bytes``: empty receipts
    (2 bytes each on the wire, ~8.4 M in 16 MiB). Returns (bytes, receipts)."""
    inner_head = b"\x09" + struct.pack("<d", time.monotonic()) + b"\x10\x01"  # report_time, index=1
    n = (max_message_bytes - margin - len(inner_head)) // 2
    inner = inner_head + b"\x2a\x00" * n  # field 5 (chunks), length 0
    size, varint = len(inner), bytearray()
    while True:
        byte = size & 0x7F
        size >>= 7
        varint.append(byte | (0x80 if size else 0))
        if not size:
            break
    return b"\x12" + bytes(varint) + inner, n


def huge_report(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    every_s: float = 3.0,
    token: str = "",
) -> AttackReport:
    """One execution report just under the server's largest message (16 MiB by default: ~8.4 M
    receipts) every ``every_s`` seconds, on an otherwise quiet stream (one observation a second,
    same index, so it is served once and adds no load of its own)."""
    report = report or AttackReport("huge_report")
    robot = Robot(address, features, report, "atk-huge-report", token=token)
    obs = Observations(features)
    payload: bytes | None = None
    last = -math.inf
    for _ in ticks(1.0, stop):
        stream = robot.connect(stop)
        if stream is None:
            break
        if payload is None:
            assert robot.response is not None
            limit = robot.response.max_message_bytes or 16 * MIB
            payload, n = huge_report_bytes(min(limit, 16 * MIB))
            report.extra["receipts per report"] = n
            report.extra["report bytes"] = len(payload)
        stream.send(obs(0, time.monotonic()))
        if time.monotonic() - last >= every_s:
            last = time.monotonic()
            if stream.send(payload, wait_s=5.0):
                report.add("huge reports")
    robot.close()
    return report


# ---- 8. never_reads ------------------------------------------------------------------------------


def never_reads(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    name_bytes: int = 64 * 1024,
    total_bytes: int = 300 * MIB,
    rate_hz: float = 190.0,
    token: str = "",
) -> AttackReport:
    """Opens its stream and never reads it, while sending observations the server must answer
    with a notice that echoes a ~64 KiB tensor name (an unknown feature): ``total_bytes`` in all,
    at ``rate_hz`` (just under the default 200 obs/s limit, so every one gets its notice). The
    stream is then held open, unread, until ``stop``."""
    report = report or AttackReport("never_reads")
    robot = Robot(address, features, report, "atk-never-reads", token=token)
    obs = Observations(features)
    long_name = "x" * name_bytes
    bogus = pb.Tensor(name=long_name, dtype="float32", shape=[1], data=b"\x00\x00\x00\x00")
    index = 0
    for _ in ticks(rate_hz, stop):
        stream = robot.connect(stop, read=False)
        if stream is None:
            break
        if report.counts["bytes"] >= total_bytes:
            continue  # sent it all: hold the unread stream open
        stream.send(obs(index, time.monotonic(), [bogus, *obs.tensors]), wait_s=0.5)
        index += 1
    report.extra["sent MiB"] = report.counts["bytes"] / MIB
    robot.close()
    return report


# ---- 9. slot_squat -------------------------------------------------------------------------------


def slot_squat(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    slots: int = 8,
    extra: int = 4,
    period_s: float = 0.5,
    token: str = "",
) -> AttackReport:
    """Registers ``slots + extra`` robot ids and never opens a stream on any, again every
    ``period_s`` (each re-registration replaces its own stale one, so none ever expires): every
    fleet slot stays taken by a registration nobody uses."""
    report = report or AttackReport("slot_squat")
    robot = Robot(address, features, report, "atk-squat", token=token)
    for _ in ticks(1.0 / period_s, stop):
        held = 0
        for k in range(slots + extra):
            if stop.is_set():
                break
            if robot.register(timeout=2.0, robot_id=f"atk-squat-{k}") is not None:
                held += 1
        report.extra["slots held last round"] = held
        report.extra["most slots held"] = max(held, report.extra.get("most slots held", 0))
    robot.close()
    return report


# ---- 10. identity --------------------------------------------------------------------------------

REFUSED_AUTH = ("UNAUTHENTICATED", "PERMISSION_DENIED")


def identity(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    fleet_token: str,
    protected_ids: tuple[str, ...],
    victim_id: str,
    victim_token: str,
    other_token: str = "",
    period_s: float = 1.0,
) -> AttackReport:
    """Identity theft with a valid fleet token:

    - registers robot ids that have their own per-robot token (``protected_ids``) with the fleet
      token: must be refused (UNAUTHENTICATED or PERMISSION_DENIED). One that gets in opens its
      stream and holds it, so the real robot cannot connect;
    - the victim registers with its own token; its fresh session is then opened by someone
      else: with the fleet token, with another robot's token (``other_token``) and with none.
      Each must be refused.
    """
    report = report or AttackReport("identity")
    held: dict[str, Robot] = {}
    rounds = 0
    for _ in ticks(1.0 / period_s, stop):
        rounds += 1
        for rid in protected_ids:
            if rid in held and held[rid].stream is not None and held[rid].stream.alive:
                continue
            thief = held.pop(rid, None) or Robot(address, features, report, rid, token=fleet_token)
            if thief.register(timeout=2.0) is not None:
                report.violation(f"fleet token registered {rid!r}, which has its own token")
                thief.open()
                held[rid] = thief
                continue
            code = _code_name(thief.error) if thief.error is not None else "?"
            if code not in REFUSED_AUTH:
                report.event(f"register {rid!r} with the fleet token: {code} (refused, but not for its credential)")
            thief.close()
        for label, credential in (("fleet token", fleet_token), ("another robot's token", other_token), ("no token", "")):
            if stop.is_set() or (label == "another robot's token" and not other_token):
                continue
            victim = Robot(address, features, report, victim_id, token=victim_token)
            deadline = time.monotonic() + 2.0
            while victim.register(timeout=2.0) is None and time.monotonic() < deadline and not stop.is_set():
                stop.wait(0.1)  # the previous attempt's session may still be closing
            if victim.response is None:
                report.event(f"victim could not register: {_code_name(victim.error) if victim.error else '?'}")
                victim.close()
                continue
            stream = victim.open(token=credential)
            stream.closed.wait(0.5)
            if stream.alive or stream.code == "OK":
                report.violation(f"stream on another robot's session with {label}: accepted")
            elif stream.code not in REFUSED_AUTH:
                report.event(f"stream on another robot's session with {label}: refused with {stream.code} ({stream.details[:120]})")
            report.code(f"hijack with {label}", stream.code or "OPEN")
            victim.close()
    report.extra["rounds"] = rounds
    for robot in held.values():
        robot.close()
    return report


# ---- 12. idle_sockets ----------------------------------------------------------------------------


def raise_fd_limit(need: int) -> int:
    """Raise this process's soft RLIMIT_NOFILE to the hard limit if below ``need``; returns it."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < need:
        target = hard if hard != resource.RLIM_INFINITY else need
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        soft = target
    return soft


def _open_idle(
    host: str, port: int, count: int, stop: threading.Event, report: AttackReport, greeting: bytes = b"", label: str = "idle sockets"
) -> list[socket.socket]:
    """Up to ``count`` TCP connections to ``host:port`` (each sends ``greeting`` and, if it sent
    one, must get an HTTP 101 back), kept open and silent; stops early when ``stop`` is set."""
    limit = raise_fd_limit(count + 256)
    report.extra["fd limit"] = limit
    socks = []
    for _ in range(min(count, max(0, limit - 128))):
        if stop.is_set():
            break
        s = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
        s.settimeout(2.0)
        try:
            s.connect((host, port))
            if greeting:
                s.sendall(greeting)
                if b" 101 " not in s.recv(4096):
                    raise OSError("no websocket upgrade")
            socks.append(s)
            report.add(f"{label} connected")
        except OSError as exc:
            s.close()
            report.add(f"{label} failed")
            report.event(f"connect failed: {exc}")
    report.extra["connected"] = len(socks)
    return socks


def _closed_by_server(socks: list[socket.socket], told: tuple[bytes, ...] = ()) -> int:
    """How many of ``socks`` the server closed (with ``told``: sent a text containing one of them)."""
    closed = 0
    for s in socks:
        s.setblocking(False)
        try:
            if not told:
                closed += s.recv(1, socket.MSG_PEEK) == b""
                continue
            while chunk := s.recv(65536):
                if any(marker in chunk for marker in told):
                    closed += 1
                    break
        except BlockingIOError:
            pass
        except OSError:
            closed += 1
    return closed


def idle_sockets(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    count: int = 1100,
) -> AttackReport:
    """``count`` TCP connections to the server's port that never send a byte, held until stop."""
    report = report or AttackReport("idle_sockets")
    host, _, port = address.rpartition(":")
    socks = _open_idle(host.strip("[]"), int(port), count, stop, report)
    try:
        stop.wait()
        # Which of them the server closed meanwhile (a handshake timeout is fine; it is not required).
        report.extra["closed by the server"] = _closed_by_server(socks)
    finally:
        for s in socks:
            s.close()
    return report


# ---- 13. garbage ---------------------------------------------------------------------------------


def jpeg_scan_bomb(height: int, width: int, scans: int = 200_000) -> bytes:
    """A valid progressive JPEG of ``height`` x ``width`` whose last refinement scan is repeated
    ``scans`` times: tiny to send, seconds of CPU to decode (libjpeg has no scan limit)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.zeros((height, width, 3), np.uint8)).save(buf, "JPEG", quality=90, progressive=True)
    data = buf.getvalue()
    i, last_scan, eoi = 2, None, None
    while i < len(data):
        marker = data[i + 1]
        if marker == 0xD9:
            eoi = i
            break
        end = i + 2 + struct.unpack(">H", data[i + 2 : i + 4])[0]
        if marker == 0xDA:  # entropy-coded data runs to the next marker that is not a stuffed 0xFF or RSTn
            while not (data[end] == 0xFF and data[end + 1] != 0 and not 0xD0 <= data[end + 1] <= 0xD7):
                end += 1
            last_scan = (i, end)
        i = end
    assert last_scan is not None and eoi is not None, "Pillow did not write a progressive JPEG"
    return data[:eoi] + data[last_scan[0] : last_scan[1]] * scans + b"\xff\xd9"


def garbage_payloads(rng: random.Random, obs: Observations) -> list[tuple[str, bytes]]:
    """Byte strings sent as stream messages that do not parse as a ``RobotMessage``."""
    valid = obs(1, time.monotonic()).SerializeToString()
    bad_utf8 = b"\x0a\x0a" + b"\x1a\x08" + b"\x0a\x02\xff\xfe" + b"\x12\x02ab"  # tensor name: invalid UTF-8
    return [
        ("random bytes", rng.randbytes(rng.randint(1, 4096))),
        ("nested groups", b"\x0b" * 100_000),
        ("truncated message", valid[: max(1, len(valid) // 2)]),
        ("length past the end", b"\x0a\xff\xff\xff\xff\x07" + b"x" * 16),
        ("varint overflow", b"\x08" + b"\xff" * 11),
        ("invalid UTF-8 string", bad_utf8),
        ("end-group without start", b"\x0c"),
        ("valid then junk", valid + rng.randbytes(32)),
    ]


def garbage(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    rate_hz: float = 5.0,
    bomb_rate_hz: float = 4.0,
    bomb_scans: int = 200_000,
    seed: int = 0,
    token: str = "",
) -> AttackReport:
    """Bytes that do not parse as protobuf on the Stream method of a registered session (a new
    session whenever the server ends the stream), and, on a second robot, observations whose
    image is a progressive-JPEG scan bomb (if the policy takes an image)."""
    report = report or AttackReport("garbage")
    rng = random.Random(seed)
    obs = Observations(features)
    image = _image_feature(features)
    bomber: threading.Thread | None = None

    def bomb() -> None:
        assert image is not None
        name, shape = image
        data = jpeg_scan_bomb(shape[0], shape[1], bomb_scans)
        report.extra["bomb bytes"] = len(data)
        tensors = [pb.Tensor(name=name, dtype="uint8", shape=list(shape), data=data, encoding=pb.JPEG) if t.name == name else t for t in obs.tensors]
        robot = Robot(address, features, report, "atk-jpeg-bomb", token=token)
        index = 0
        for _ in ticks(bomb_rate_hz, stop):
            stream = robot.connect(stop)
            if stream is None:
                break
            if stream.send(obs(index, time.monotonic(), tensors), wait_s=0.2):
                report.add("scan bombs")
            index += 1
        robot.close()

    if image is not None and bomb_rate_hz > 0:
        bomber = threading.Thread(target=bomb, name="adversary-jpeg-bomb", daemon=True)
        bomber.start()
    robot = Robot(address, features, report, "atk-garbage", token=token)
    for _ in ticks(rate_hz, stop):
        stream = robot.connect(stop)
        if stream is None:
            break
        kind, payload = rng.choice(garbage_payloads(rng, obs))
        stream.send(payload)
        report.add(f"garbage: {kind}")
        stream.closed.wait(0.1)
    robot.close()
    if bomber is not None:
        bomber.join(timeout=10)
    return report


# ---- 14. openpi_idle ---------------------------------------------------------------------------


def _ws_upgrade(host: str, port: int) -> bytes:
    """A websocket client's opening handshake (HTTP upgrade request) to ``host:port``."""
    return (
        f"GET / HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    ).encode()


def openpi_idle(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    port: int,
    count: int = 1000,
) -> AttackReport:
    """``count`` websocket connections to the openpi port (``port`` on ``address``'s host) that
    complete the handshake and never send a request, held until stop. A server that makes each
    connection a robot fills its slots with them; one that registers on the first request does not."""
    report = report or AttackReport("openpi_idle")
    host = address.rpartition(":")[0].strip("[]")
    upgrade = _ws_upgrade(host, port)
    socks = _open_idle(host, port, count, stop, report, upgrade, "websocket connections")
    try:
        stop.wait()
        # The server's text before it closes them: "no request within ..." or "... refused this client".
        report.extra["told and closed by the server"] = _closed_by_server(socks, (b"no request within", b"refused this client"))
    finally:
        for s in socks:
            s.close()
    return report


# ---- 15. openpi_garbage ------------------------------------------------------------------------


def _ws_frame(payload: bytes, opcode: int = 2) -> bytes:
    """One masked websocket frame from a client (opcode 2: binary, 1: text)."""
    n = len(payload)
    if n < 126:
        length = bytes([0x80 | n])
    elif n < 1 << 16:
        length = bytes([0x80 | 126]) + struct.pack("!H", n)
    else:
        length = bytes([0x80 | 127]) + struct.pack("!Q", n)
    mask = b"\x5a\xa5\x3c\xc3"
    body = (np.frombuffer(payload, np.uint8) ^ np.resize(np.frombuffer(mask, np.uint8), n)).tobytes() if n else b""
    return bytes([0x80 | opcode]) + length + mask + body


def openpi_payloads(rng: random.Random) -> list[tuple[int, bytes]]:
    """(opcode, payload) frames an openpi endpoint must refuse, each for its own reason."""
    import msgpack

    def array(data: bytes, dtype: str, shape: list[int]) -> dict:
        return {b"__ndarray__": True, b"data": data, b"dtype": dtype, b"shape": shape}

    state = {"observation/state": array(b"\0" * 16, "<f8", [2])}
    return [
        (2, rng.randbytes(rng.randint(1, 4096))),  # not msgpack at all
        (1, "not a binary frame " * 20),  # text
        (2, msgpack.packb({"observation/state": array(b"\0" * 8, "<f8", [10**9])})),  # shape far beyond its bytes
        (2, msgpack.packb({"observation/state": array(b"\0" * 8, "|O", [1])})),  # object dtype
        (2, msgpack.packb({"observation/state": array(b"\0" * 8, ">f8", [1])})),  # big-endian
        (2, msgpack.packb({"observation/state": array(b"\0" * 8, "<f8", [1] * 40)})),  # too many dims
        (2, msgpack.packb({"observation/state": msgpack.ExtType(1, b"pickle?")})),  # extension type
        (2, msgpack.packb([[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[0]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]])),  # deep nesting
        (2, msgpack.packb({str(k): k for k in range(5000)})),  # a map past the container bound
        (2, msgpack.packb(state)),  # decodes, but is not the policy's observation (no image)
    ]


def openpi_garbage(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    port: int,
    seed: int = 0,
) -> AttackReport:
    """One openpi connection that sends malformed frames as fast as the server takes them and
    never reads a reply: every frame must be refused (a text frame each) and nobody else notice."""
    report = report or AttackReport("openpi_garbage")
    rng = random.Random(seed)
    host = address.rpartition(":")[0].strip("[]")
    upgrade = _ws_upgrade(host, port)
    socks = _open_idle(host, port, 1, stop, report, upgrade, "websocket connections")
    if not socks:
        return report
    sock = socks[0]
    sent = 0
    try:
        while not stop.is_set():
            for opcode, payload in openpi_payloads(rng):
                try:
                    sock.sendall(_ws_frame(payload if isinstance(payload, bytes) else payload.encode(), opcode))
                    sent += 1
                    report.add("garbage frames sent")
                except TimeoutError:
                    report.add("sends blocked (the server stopped reading: it waits on its unread replies)")
                except OSError as exc:
                    report.event(f"connection ended: {exc}")
                    report.extra["garbage frames"] = sent
                    return report
                if stop.is_set():
                    break
        report.extra["garbage frames"] = sent
    finally:
        sock.close()
    return report


# ---- 16. openpi_never_reads --------------------------------------------------------------------


def openpi_observation(features: Features, task: str = "pick up the block") -> dict[str, Any]:
    """A valid openpi request for a policy with ``features``: each feature under its own name
    (the endpoint's key map takes it), zeros, and a prompt."""
    return {**{name: np.zeros(shape, dtype=dtype) for name, (dtype, shape) in features.items()}, "prompt": task}


def _send_frame(sock: socket.socket, data: bytes, stop: threading.Event, report: AttackReport) -> bool:
    """All of ``data`` (one frame: a frame cut in two would be a protocol error, not the attack),
    waiting as long as the server's receive window stays shut; False if ``stop`` came first."""
    view = memoryview(data)
    blocked = False
    while view:
        if stop.is_set():
            return False
        try:
            view = view[sock.send(view) :]
        except TimeoutError:
            if not blocked:
                report.add("sends blocked (the server stopped reading)")
                blocked = True
    return True


def openpi_never_reads(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    port: int,
    connections: int = 3,
    rcvbuf: int = 4096,
) -> AttackReport:
    """``connections`` openpi connections that send valid requests as fast as the server takes
    them and never read a byte back (a 4 KiB receive window, so that the server's replies back up
    soon). A connection the server ends is opened again. The stand-in is :func:`openpi_honest`
    with as many connections."""
    report = report or AttackReport("openpi_never_reads")
    from lerobot_armory.entrypoints.openpi.codec import pack

    host = address.rpartition(":")[0].strip("[]")
    upgrade = _ws_upgrade(host, port)
    frame = _ws_frame(pack(openpi_observation(features)))
    report.extra["request bytes"] = len(frame)
    socks: list[socket.socket] = []
    lock = threading.Lock()

    def one(k: int) -> None:
        while not stop.is_set():
            s = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)  # before connect: the window it advertises
            s.settimeout(1.0)
            try:
                s.connect((host, port))
                s.sendall(upgrade)
                # The 101 and the server's metadata frame: the last bytes this client reads.
                if b" 101 " not in s.recv(4096):
                    raise OSError("no websocket upgrade")
            except OSError as exc:
                s.close()
                report.add("connections failed")
                report.event(f"connect failed: {exc}")
                stop.wait(0.3)
                continue
            report.add("connections opened")
            with lock:
                socks.append(s)
            try:
                while _send_frame(s, frame, stop, report):
                    report.add("requests sent")
            except OSError as exc:
                report.add("connections ended by the server")
                report.event(f"connection ended: {type(exc).__name__}: {exc}")
                stop.wait(0.3)

    threads = [threading.Thread(target=one, args=(k,), name=f"openpi-never-reads-{k}", daemon=True) for k in range(connections)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    import fcntl
    import termios

    unread = []
    for s in socks:  # what the server sent that nobody read, as it sits in this side's receive buffers
        with contextlib.suppress(OSError):
            unread.append(struct.unpack("i", fcntl.ioctl(s.fileno(), termios.FIONREAD, b"\0\0\0\0"))[0])
        s.close()
    report.extra["unread reply bytes (open connections)"] = sum(unread)
    report.extra["requests sent"] = report.counts["requests sent"]
    return report


def openpi_honest(
    address: str,
    stop: threading.Event,
    features: Features,
    report: AttackReport | None = None,
    *,
    port: int,
    connections: int = 3,
) -> AttackReport:
    """The honest stand-in of :func:`openpi_never_reads`: ``connections`` openpi clients that send
    the same request, read each reply, and ask again at once (openpi's client in a loop)."""
    report = report or AttackReport("openpi_honest")
    from websockets.sync.client import connect

    from lerobot_armory.entrypoints.openpi.codec import pack

    host = address.rpartition(":")[0].strip("[]")
    request = pack(openpi_observation(features))

    def one(k: int) -> None:
        while not stop.is_set():
            try:
                with connect(f"ws://{host}:{port}", compression=None, max_size=None, open_timeout=10) as ws:
                    ws.recv(timeout=10)  # the server's metadata
                    report.add("connections opened")
                    while not stop.is_set():
                        ws.send(request)
                        reply = ws.recv(timeout=30)
                        report.add("chunks" if isinstance(reply, bytes) else "refusals")
                        if isinstance(reply, str):
                            report.event(reply[:200])
            except Exception as exc:  # noqa: BLE001 - a connection the server ends is opened again
                if not stop.is_set():
                    report.add("connections ended")
                    report.event(f"connection ended: {type(exc).__name__}: {str(exc)[:160]}")
                    stop.wait(0.3)

    threads = [threading.Thread(target=one, args=(k,), name=f"openpi-honest-{k}", daemon=True) for k in range(connections)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return report


# The honest stand-ins of attackers whose baseline is not an armory_sim robot.
STANDINS: dict[str, Callable[..., AttackReport]] = {
    "openpi_honest": openpi_honest,
    "share_lean": functools.partial(share_liar, honest=True),
    # share_liar's baseline: an honest lean client in the liar's place, beside its lean twin.
    "share_lean_pair": functools.partial(share_liar, honest=True, robot_id="standin", lean_twin=True),
}


SCENARIOS: dict[str, Callable[..., AttackReport]] = {
    "clock_nan": clock_nan,
    "capture_absurd": capture_absurd,
    "report_absurd": report_absurd,
    "fps_absurd": fps_absurd,
    "priority_flood": priority_flood,
    "clock_ahead": clock_ahead,
    "share_liar": share_liar,
    "share_lean": functools.partial(share_liar, honest=True),
    "huge_report": huge_report,
    "never_reads": never_reads,
    "slot_squat": slot_squat,
    "identity": identity,
    "idle_sockets": idle_sockets,
    "garbage": garbage,
    "openpi_idle": openpi_idle,
    "openpi_garbage": openpi_garbage,
    "openpi_never_reads": openpi_never_reads,
}


# ---- honest robots -------------------------------------------------------------------------------


class SteppedClock:
    """``time.monotonic()``, plus ``step_s`` from ``at`` (a monotonic time) on: a robot clock
    that an NTP step or a manual setting moved while the robot ran."""

    def __init__(self, step_s: float, at: float) -> None:
        self.step_s, self.at = step_s, at

    def __call__(self) -> float:
        now = time.monotonic()
        return now + self.step_s if now >= self.at else now


@dataclass
class Timeline:
    """One robot's ticks: when (seconds from its start, on the real clock) and whether it executed."""

    times: list[float] = field(default_factory=list)
    executed: list[int] = field(default_factory=list)
    first_chunk_s: float | None = None
    chunks: list[int] = field(default_factory=list)  # chunks received so far, at each tick

    def chunks_per_s(self, start: float = 0.0, end: float = math.inf) -> float | None:
        """Chunks received per second between the first and the last tick inside ``[start, end)``."""
        inside = [(t, c) for t, c in zip(self.times, self.chunks, strict=True) if start <= t < end]
        if len(inside) < 2 or inside[-1][0] <= inside[0][0]:
            return None
        return (inside[-1][1] - inside[0][1]) / (inside[-1][0] - inside[0][0])

    def starvation_pct(self, start: float = 0.0, end: float = math.inf) -> float | None:
        """Starved ticks / ticks inside ``[start, end)``, in % (None: no tick there)."""
        inside = [e for t, e in zip(self.times, self.executed, strict=True) if start <= t < end]
        return 100.0 * (len(inside) - sum(inside)) / len(inside) if inside else None


def run_ticks(client: Any, duration_s: float, timeline: Timeline | None = None, report_every_s: float = 0.2) -> Timeline:
    """``ArmoryClient.run``'s loop, ticking on the real monotonic clock whatever the client's own
    (possibly stepped) clock says, from now on, connected or not: the client connects on a
    background thread (``client.connect``: with its own back-off) and ticks before it is
    connected starve. Returns the timeline; a refused connection is in ``client.fatal``."""
    timeline = timeline or Timeline()

    def connect() -> None:
        try:
            client.connect()
        except Exception as exc:  # noqa: BLE001 - refused or unreachable: the robot starves
            client.fatal = exc

    threading.Thread(target=connect, name="honest-connect", daemon=True).start()
    period = 1.0 / client.identity.fps
    start = time.monotonic()
    next_tick = last_report = start
    while True:
        now = time.monotonic()
        if now - start >= duration_s:
            break
        if now < next_tick:
            time.sleep(min(next_tick - now, 0.05))
            continue
        timeline.times.append(round(now - start, 4))
        timeline.executed.append(1 if client.step() else 0)
        timeline.chunks.append(client.chunks_received)
        if timeline.first_chunk_s is None and client.chunks_received:
            timeline.first_chunk_s = round(now - start, 4)
        if now - last_report >= report_every_s:
            client.report()
            last_report = now
        next_tick += period
        if time.monotonic() - next_tick > period:  # overran: no burst to catch up
            next_tick = time.monotonic()
    client.report()
    return timeline


def run_honest_robot(spec: dict[str, Any], group: dict[str, Any], address: str, t0: float) -> dict[str, Any]:
    """One ``armory_sim`` robot as ``lerobot_armory.bench.robots.run_robot`` builds it, with an
    optional auth token and stepped clock, ticking from now for the group's duration."""
    from lerobot_armory.network_delay import LogNormalDelay
    from lerobot_armory.robot.armory_sim import ArmorySim, ArmorySimConfig
    from lerobot_armory.robot.client import ArmoryClient, Backoff, RobotIdentity
    from lerobot_armory.robot.features import FeatureMap
    from lerobot_armory.robot.netem import NetworkEmulator

    robot = ArmorySim(ArmorySimConfig(scene=spec["scene"], image_size=group["image_size"], seed=spec["seed"]))
    fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
    net = LogNormalDelay(group["net_median_ms"] / 1000.0, group["net_sigma"])
    network = (lambda: NetworkEmulator(net, net, seed=spec["seed"])) if group["net_median_ms"] > 0 else None
    step = float(spec.get("clock_step_s", 0.0))
    clock = SteppedClock(step, t0 + float(spec.get("clock_step_at_s", 0.0))) if step else time.monotonic
    client = ArmoryClient(
        address,
        RobotIdentity(spec["robot_id"], spec["fps"], spec["h_min"], spec["h_max"], spec["weight"], spec["tier"], spec["scene"]),
        fmap.wire_features(),
        observe=lambda: fmap.to_wire(robot.get_observation()),
        act=lambda vector: robot.send_action(fmap.to_action(vector)),
        clock=clock,
        backoff=Backoff(0.2, 1.0, give_up_s=30.0),
        network=network,
        token=spec.get("token", ""),
    )
    robot.connect()
    try:
        timeline = run_ticks(client, group["duration_s"])
        stats = client.stats()
    finally:
        client.close()
        robot.disconnect()
    stats.update(robot.task_stats())
    minutes = stats["ticks"] / spec["fps"] / 60.0
    stats["successes_per_min"] = stats["successes"] / minutes if minutes else 0.0
    stats.update({k: spec[k] for k in ("scene", "fps", "h_min", "h_max", "weight")})
    stats["clock_step_s"] = step
    stats["clock_step_at_s"] = float(spec.get("clock_step_at_s", 0.0))
    stats["first_chunk_s"] = timeline.first_chunk_s
    stats["tick_times"] = timeline.times
    stats["executed"] = "".join(map(str, timeline.executed))
    stats["chunks_at_tick"] = timeline.chunks
    stats["error"] = f"{type(client.fatal).__name__}: {client.fatal}" if client.fatal is not None else None
    stats["notices"] = Counter(client.notices).most_common(5)
    return stats


def honest_group(path: str) -> None:
    """``python tests/support/adversaries.py honest SPEC.json``: build, say ready, wait for go, run.

    SPEC: ``duration_s``, ``stats_dir``, ``image_size``, ``net_median_ms``, ``net_sigma``,
    ``ready_file`` (written once imports are done), ``go_file`` (waited for; holds the server
    address), ``robots`` (robot_id, tier, scene, fps, h_min, h_max, weight, seed, optional
    token, clock_step_s, clock_step_at_s).
    """
    import logging

    group = json.loads(Path(path).read_text())
    logging.basicConfig(level=logging.ERROR, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    for module in ("lerobot_armory.robot.armory_sim", "lerobot_armory.robot.client"):
        importlib.import_module(module)  # the slow imports, before "ready"

    Path(group["ready_file"]).write_text("ready")
    go = Path(group["go_file"])
    deadline = time.monotonic() + 300
    while not go.exists() or not go.read_text().strip():
        if time.monotonic() > deadline:
            sys.exit("honest group: no go file after 300 s")
        time.sleep(0.005)
    address = go.read_text().strip()
    t0 = time.monotonic()
    from lerobot_armory.bench.robots import run_all

    run_all(group["robots"], lambda spec: run_honest_robot(spec, group, address, t0), Path(group["stats_dir"]))

if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "honest":
        honest_group(sys.argv[2])
    else:
        sys.exit("usage: python tests/support/adversaries.py honest SPEC.json")
