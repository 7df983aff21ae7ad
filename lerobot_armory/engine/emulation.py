"""Latency-profile emulation: replay a GPU's ``d_infer(b)`` on any machine.

The wrapped engine runs the real policy, then holds the batch until the profiled time for that
batch size has passed since the batch started. Chunks are real; only their timing is the
profile's. Every output of such a run says "emulated latency" next to the profile name.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.engine.protocol import Engine


class EmulatedLatencyEngine:
    """Runs ``engine`` and pads every batch to the profile's latency for its size."""

    def __init__(self, engine: Engine, profile: LatencyProfile, sleep=time.sleep, clock=time.perf_counter) -> None:
        self.engine = engine
        self.profile = profile
        self.sleep = sleep
        self.clock = clock
        self.batches = 0
        self.overruns = 0  # batches where the real model was slower than the profile
        self.worst_overrun_ms = 0.0

    @property
    def label(self) -> str:
        return f"{self.profile.name} (emulated latency)"

    @property
    def rtc(self) -> Any:
        """The wrapped engine's RTC processor (None: no real-time chunking)."""
        return self.engine.rtc

    @property
    def history_steps(self) -> int:
        """The wrapped engine's observations per row."""
        return self.engine.history_steps

    @property
    def unrecorded_batches(self) -> int:
        """The wrapped engine's."""
        return self.engine.unrecorded_batches

    def infer(
        self,
        observations: Sequence[dict[str, np.ndarray]],
        tasks: Sequence[str],
        noise_seeds: Sequence[int] | None = None,
        history: Sequence[Sequence[dict[str, np.ndarray]]] | None = None,
    ) -> np.ndarray:
        start = self.clock()
        out = self.engine.infer(observations, tasks, noise_seeds, history)
        self._hold(start, len(observations))
        return out

    def infer_guided(
        self,
        observations: Sequence[dict[str, np.ndarray]],
        tasks: Sequence[str],
        noise_seeds: Sequence[int] | None,
        prefixes: Sequence[Any],
    ) -> tuple[np.ndarray, np.ndarray]:
        start = self.clock()
        out = self.engine.infer_guided(observations, tasks, noise_seeds, prefixes)
        self._hold(start, len(observations))
        return out

    def _hold(self, start: float, size: int) -> None:
        """Sleep until the profile's latency for ``size`` has passed since ``start``."""
        target = self.profile.latency_s(size)
        remaining = target - (self.clock() - start)
        self.batches += 1
        if remaining > 0:
            self.sleep(remaining)
        else:
            self.overruns += 1
            self.worst_overrun_ms = max(self.worst_overrun_ms, -remaining * 1000.0)
