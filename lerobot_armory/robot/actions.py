"""The robot's action buffer: which action to execute at index ``i`` (docs/spec.md §2, naive async).

Pure bookkeeping, no I/O: chunks go in as they arrive; at each tick the robot asks for the
action at its current index and gets the action from the *newest* arrived chunk covering it,
never beyond the chunk's first ``h_max`` actions. Each chunk's fate (first executed index, or
never executed) is kept for the execution reports the server uses to estimate delays.

It also measures the *seams*: at every switch from the chunk being executed to a newer one, the
jump ``‖a_new(i) − a_old(i)‖`` between the two chunks' actions at the switch index ``i`` (what the
arm would have done against what it does). A large jump is the discontinuity real-time chunking
removes; switches after the old chunk ran out (the robot starved in between) have no old action
at ``i`` and are counted apart.
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# Seam jumps kept for the percentile (the mean covers every switch): hours of switches at 30 Hz.
MAX_SEAMS_KEPT = 10_000


@dataclass
class BufferedChunk:
    chunk_id: int
    i_start: int
    actions: np.ndarray  # (H, action_dim)
    arrival_time: float
    first_executed: int | None = None  # offset into the chunk of its first executed action
    session: int = 0  # the client's session epoch the chunk arrived in

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
    seams: deque = field(default_factory=lambda: deque(maxlen=MAX_SEAMS_KEPT))  # recent seam jumps
    seam_count: int = 0
    seam_sum: float = 0.0
    switches_after_gap: int = 0  # switches where the old chunk had no action at the switch index
    # (new chunk's i_start, offset of its first executed action, jump) of the recent seams: lets a
    # benchmark relate each seam to what the server predicted for that chunk (RTC's delay).
    seam_log: deque = field(default_factory=lambda: deque(maxlen=MAX_SEAMS_KEPT))
    _current: BufferedChunk | None = None  # the chunk the last executed action came from
    session: int = 0  # the client's session epoch: chunks added now belong to it

    @property
    def current(self) -> BufferedChunk | None:
        """The chunk the last executed action came from."""
        return self._current

    def add(self, chunk_id: int, i_start: int, actions: np.ndarray, arrival_time: float) -> None:
        """A chunk arrived (robot clock), in the current ``session``."""
        self.chunks.append(BufferedChunk(chunk_id, i_start, actions, arrival_time, session=self.session))
        self.received += 1

    def add_unused(self, chunk_id: int, arrival_time: float) -> None:
        """A chunk arrived that will never be executed (computed for an earlier episode): only its
        receipt is kept, so the server still learns when it arrived."""
        self.received += 1
        self.first_executed_index["unused"] += 1
        self.pending_receipts.append((chunk_id, arrival_time, -1, self.session))

    def drop_chunks(self) -> None:
        """Forget every chunk held, keeping their receipts (an episode ended: the old world's
        chunks must never run, but the server still wants to know when they arrived)."""
        for c in self.chunks:
            self._retire(c)
        self.chunks = []
        self._current = None  # the next episode's first chunk is no seam

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
        if best is not self._current:
            self._seam(self._current, best, index)
            self._current = best
        if best.first_executed is None:
            best.first_executed = index - best.i_start
            self.first_executed_index[str(best.first_executed)] += 1
            self.pending_receipts.append((best.chunk_id, best.arrival_time, best.first_executed, best.session))
        return best.actions[index - best.i_start]

    def _seam(self, old: BufferedChunk | None, new: BufferedChunk, index: int) -> None:
        """Record the jump of a switch from ``old`` to ``new`` at ``index`` (none for the first chunk)."""
        if old is None:
            return
        k = index - old.i_start
        if not 0 <= k < len(old.actions):
            self.switches_after_gap += 1
            return
        jump = float(np.linalg.norm(np.asarray(new.actions[index - new.i_start], np.float64) - old.actions[k]))
        self.seams.append(jump)
        self.seam_log.append((new.i_start, index - new.i_start, jump))
        self.seam_count += 1
        self.seam_sum += jump

    def seam_stats(self) -> dict[str, Any]:
        """``seam_jump_mean`` (every switch), ``seam_jump_p95`` (the last MAX_SEAMS_KEPT), counts;
        None where no switch happened."""
        kept = np.fromiter(self.seams, float) if self.seams else None
        return {
            "seam_jump_mean": self.seam_sum / self.seam_count if self.seam_count else None,
            "seam_jump_p95": float(np.percentile(kept, 95)) if kept is not None else None,
            "seams": self.seam_count,
            "switches_after_gap": self.switches_after_gap,
            "seam_log": [list(x) for x in self.seam_log],
        }

    def _retire(self, c: BufferedChunk) -> None:
        if c.first_executed is None:
            self.first_executed_index["unused"] += 1
            self.pending_receipts.append((c.chunk_id, c.arrival_time, -1, c.session))

    def take_receipts(self, session: int | None = None) -> list[tuple[int, float, int]]:
        """Receipts not reported yet (cleared): ``(chunk_id, arrival_time, first_executed or -1)``.

        With ``session``, only that session's: chunk ids restart with each session, so a chunk
        kept across a move must not be reported to the new server as one of its own.
        """
        out, self.pending_receipts = self.pending_receipts, []
        return [(c, a, f) for c, a, f, s in out if session is None or s == session]

    def clear(self) -> None:
        """Forget every chunk and every receipt (after a reconnect, old chunks must never run and
        the new server knows none of them)."""
        self.drop_chunks()
        self.pending_receipts = []
