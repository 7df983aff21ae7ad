"""Client-side network emulation: per-request log-normal uplink and downlink delays.

Exactly the simulator's model (:class:`~lerobot_armory.network_delay.LogNormalDelay`, drawn
independently per message), applied to the real protocol: every observation and report waits its
uplink delay before it enters the gRPC stream, every chunk waits its downlink delay before the
robot sees it. Live and simulated runs are therefore comparable.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections.abc import Callable

import numpy as np

from lerobot_armory.network_delay import LogNormalDelay


class DelayLine:
    """Runs callbacks at given times on one background thread (order by due time)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._seq = itertools.count()
        self._cond = threading.Condition()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="armory-netem", daemon=True)
        self._thread.start()

    def call_at(self, due: float, fn: Callable[[], None]) -> None:
        with self._cond:
            heapq.heappush(self._heap, (due, next(self._seq), fn))
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._closed and (not self._heap or self._heap[0][0] > self.clock()):
                    timeout = None if not self._heap else max(0.0, self._heap[0][0] - self.clock())
                    self._cond.wait(timeout)
                if self._closed:
                    return
                _, _, fn = heapq.heappop(self._heap)
            fn()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify()


class NetworkEmulator:
    """Delays messages of one connection: ``uplink`` for robot → server, ``downlink`` back."""

    def __init__(self, uplink: LogNormalDelay, downlink: LogNormalDelay, seed: int = 0, clock: Callable[[], float] = time.monotonic) -> None:
        self.uplink = uplink
        self.downlink = downlink
        self.rng = np.random.default_rng(seed)
        self.clock = clock
        self.line = DelayLine(clock)
        self._lock = threading.Lock()

    def _draw(self, model: LogNormalDelay) -> float:
        with self._lock:
            return float(model.sample(self.rng))

    def send(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` (which enqueues a message) after an uplink delay."""
        self.line.call_at(self.clock() + self._draw(self.uplink), fn)

    def receive(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` (which hands a message to the robot) after a downlink delay."""
        self.line.call_at(self.clock() + self._draw(self.downlink), fn)

    def close(self) -> None:
        self.line.close()
