"""``ArmoryClient``: the robot's control loop against an armory server.

At every tick (``fps``): capture the observation, push it to the server, then execute the action
for the current index from the newest arrived chunk covering it — or starve (nothing goes to the
motors, the index stays). Execution reports (what arrived when, what was executed first) go back
a few times a second so the server can estimate delays without synchronised clocks.

The loop is independent of any hardware: it takes ``observe()`` and ``act(action)`` callables,
so a LeRobot robot, a simulated robot or a test double plug in the same way.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import grpc
import numpy as np

from lerobot_armory.robot.actions import ActionBuffer
from lerobot_armory.robot.connection import Connection, ReceivedChunk

log = logging.getLogger(__name__)

REPORT_EVERY_S = 0.2


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
    ) -> None:
        self.address = address
        self.identity = identity
        self.features = dict(features)
        self.observe = observe
        self.act = act
        self.clock = clock
        self.sleep = sleep
        self.jpeg_quality = jpeg_quality
        self.buffer = ActionBuffer(identity.h_max)
        self._lock = threading.Lock()
        self.index = 0
        self.ticks = 0
        self.executed = 0
        self.starved = 0
        self.notices: list[str] = []
        self.connection: Connection | None = None
        self._stop = threading.Event()

    # ---- connection --------------------------------------------------------------------------

    def connect(self, timeout: float = 10.0) -> None:
        """Register and open the stream. Raises RegistrationRefused with the server's reason."""
        conn = Connection(self.address, self.clock)
        if not conn.wait_ready(timeout):
            conn.close()
            raise ConnectionError(f"server {self.address} is unreachable")
        ident = self.identity
        try:
            reg = conn.register(ident.robot_id, self.features, ident.fps, ident.h_min, ident.h_max, ident.weight, ident.tier, ident.task)
        except grpc.RpcError as exc:
            conn.close()
            if exc.code() in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                raise ConnectionError(f"server {self.address} is unreachable: {exc.details()}") from None
            raise RegistrationRefused(f"{exc.code().name}: {exc.details()}") from None
        log.info("registered as %s with %s (H=%d)", ident.robot_id, reg.policy, reg.chunk_size)
        conn.open_stream(self._on_chunk, self._on_notice)
        self.connection = conn

    def _on_chunk(self, chunk: ReceivedChunk) -> None:
        with self._lock:
            self.buffer.add(chunk.chunk_id, chunk.i_start, chunk.actions, chunk.arrival_time)

    def _on_notice(self, notice: Any) -> None:
        self.notices.append(notice.message)
        log.warning("server notice: %s", notice.message)

    # ---- the control loop --------------------------------------------------------------------

    def step(self) -> bool:
        """One control tick: observe, push, execute or starve. Returns True if it executed."""
        assert self.connection is not None
        t = self.clock()
        obs = self.observe()
        self.connection.send_observation(self.index, obs, capture_time=t, jpeg_quality=self.jpeg_quality)
        with self._lock:
            action = self.buffer.action_for(self.index)
        self.ticks += 1
        if action is None:
            self.starved += 1
            return False
        self.act(action)
        self.index += 1
        self.executed += 1
        return True

    def report(self) -> None:
        """Send an execution report with every chunk receipt not yet reported."""
        assert self.connection is not None
        with self._lock:
            receipts = self.buffer.take_receipts()
        self.connection.send_report(self.index, self.executed, self.starved, receipts)

    def run(self, duration_s: float = 0.0) -> dict[str, Any]:
        """Connect if needed and run ticks until ``duration_s`` (0: until :meth:`stop`)."""
        if self.connection is None:
            self.connect()
        period = 1.0 / self.identity.fps
        start = self.clock()
        next_tick = start
        last_report = start
        while not self._stop.is_set():
            now = self.clock()
            if duration_s and now - start >= duration_s:
                break
            if now < next_tick:
                self.sleep(next_tick - now)
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
        self._stop.set()

    def close(self) -> None:
        if self.connection is not None:
            self.connection.close()
            self.connection = None

    def stats(self) -> dict[str, Any]:
        """The stats JSON of the run so far."""
        with self._lock:
            first = dict(self.buffer.first_executed_index)
            received = self.buffer.received
        return {
            "robot_id": self.identity.robot_id,
            "ticks": self.ticks,
            "executed_steps": self.executed,
            "starved_steps": self.starved,
            "starvation_pct": 100.0 * self.starved / self.ticks if self.ticks else 0.0,
            "chunks_received": received,
            "first_executed_index": first,
        }
