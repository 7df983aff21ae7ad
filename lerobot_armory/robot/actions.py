"""The robot's action buffer: which action to execute at index ``i`` (SPEC §2, naive async).

Pure bookkeeping, no I/O: chunks go in as they arrive; at each tick the robot asks for the
action at its current index and gets the action from the *newest* arrived chunk covering it,
never beyond the chunk's first ``h_max`` actions. Each chunk's fate (first executed index, or
never executed) is kept for the execution reports the server uses to estimate delays.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np


@dataclass
class BufferedChunk:
    chunk_id: int
    i_start: int
    actions: np.ndarray  # (H, action_dim)
    arrival_time: float
    first_executed: int | None = None  # offset into the chunk of its first executed action

    def covers(self, index: int, h_max: int) -> bool:
        return self.i_start <= index < self.i_start + min(h_max, len(self.actions))


@dataclass
class ActionBuffer:
    """Chunks received in the current session, and the receipts still to report.

    Attributes:
        h_max: actions of a chunk the robot may execute.
    """

    h_max: int
    chunks: list[BufferedChunk] = field(default_factory=list)
    pending_receipts: list[tuple[int, float, int]] = field(default_factory=list)
    first_executed_index: Counter = field(default_factory=Counter)
    received: int = 0

    def add(self, chunk_id: int, i_start: int, actions: np.ndarray, arrival_time: float) -> None:
        """A chunk arrived (robot clock)."""
        self.chunks.append(BufferedChunk(chunk_id, i_start, actions, arrival_time))
        self.received += 1

    def action_for(self, index: int) -> np.ndarray | None:
        """The action to execute at ``index``, or None (the robot starves this tick).

        Also retires chunks that can no longer be executed (their usable range is behind the
        index), recording their receipts.
        """
        best: BufferedChunk | None = None
        keep = []
        for c in self.chunks:
            if c.i_start + min(self.h_max, len(c.actions)) <= index:
                self._retire(c)
                continue
            keep.append(c)
            if c.covers(index, self.h_max) and (best is None or (c.i_start, c.chunk_id) > (best.i_start, best.chunk_id)):
                best = c
        self.chunks = keep
        if best is None:
            return None
        if best.first_executed is None:
            best.first_executed = index - best.i_start
            self.first_executed_index[str(best.first_executed)] += 1
            self.pending_receipts.append((best.chunk_id, best.arrival_time, best.first_executed))
        return best.actions[index - best.i_start]

    def _retire(self, c: BufferedChunk) -> None:
        if c.first_executed is None:
            self.first_executed_index["unused"] += 1
            self.pending_receipts.append((c.chunk_id, c.arrival_time, -1))

    def take_receipts(self) -> list[tuple[int, float, int]]:
        """Receipts not reported yet (cleared)."""
        out, self.pending_receipts = self.pending_receipts, []
        return out

    def clear(self) -> None:
        """Forget every chunk (after a reconnect, old chunks must never run)."""
        for c in self.chunks:
            self._retire(c)
        self.chunks = []
        self.pending_receipts = []
