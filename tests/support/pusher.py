"""A live robot double for the server tests: :class:`Pusher` pushes a distinct observation
(``observation(robot, index)``) every period and keeps its chunks; ``wait_for`` polls a condition.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from lerobot_armory.robot.connection import Connection

STATE = "observation.state"
IMAGE = "observation.images.front"


def features(engine):
    return {f.name: (f.dtype, f.shape) for f in engine.wire_features}


def observation(robot: int, index: int) -> dict[str, np.ndarray]:
    """A distinct, reproducible observation per (robot, index)."""
    rng = np.random.default_rng(1000 * robot + index)
    return {
        STATE: rng.standard_normal(2).astype(np.float32),
        IMAGE: rng.integers(0, 256, (32, 32, 3), dtype=np.uint8),
    }


class Pusher:
    """A robot double: pushes a new observation every period and keeps chunks; like a real robot,
    its index moves (one step per period) only over actions it received."""

    def __init__(self, address: str, engine, k: int, period: float = 0.03, robot_id: str | None = None) -> None:
        self.k = k
        self.conn = Connection(address)
        self.conn.register(robot_id or f"pusher{k}", features(engine), fps=1 / period, h_min=1, h_max=10, tier="fast")
        self.chunks = []
        self.notices = []
        self.closed_with = None
        self.conn.open_stream(self.chunks.append, self.notices.append, self._closed)
        self.period = period
        self.index = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _closed(self, err):
        self.closed_with = err

    def start(self):
        self._thread.start()
        return self

    def _run(self):
        while not self._stop.is_set():
            self.conn.send_observation(self.index, observation(self.k, self.index))
            if any(c.i_start <= self.index < c.i_start + 10 for c in list(self.chunks)):
                self.index += 1
            time.sleep(self.period)

    def stop(self):
        self._stop.set()
        self._thread.join()
        self.conn.close()


def wait_for(cond, timeout=10.0, step=0.02):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(step)
    return False
