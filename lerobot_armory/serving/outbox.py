"""One robot's outbox: what the serving loop hands it, waiting for its entrypoint to send."""

from __future__ import annotations

import collections
import threading
from collections.abc import Callable

from lerobot_armory.serving.messages import ChunkOut, ServerMessage

# What one robot's outbox may hold: a robot that never reads its stream costs at most this much
# server memory (notices are short: their text is cut at MAX_NOTICE_CHARS).
OUTBOX_CHUNKS = 8
OUTBOX_NOTICES = 16
MAX_NOTICE_CHARS = 300


class Outbox:
    """Messages waiting to be written to one robot's stream.

    Never blocks the producer (the serving loop) and never grows without bound: if the robot stops
    reading, the oldest *chunk* is dropped once ``limit`` messages wait (a newer chunk supersedes
    it anyway), and the oldest *notice* once ``notice_limit`` notices wait. ``get`` returns None
    once closed and drained.
    """

    def __init__(self, limit: int = OUTBOX_CHUNKS, notice_limit: int = OUTBOX_NOTICES) -> None:
        self._items: collections.deque[ServerMessage] = collections.deque()
        self._cond = threading.Condition()
        self._closed = False
        self.limit = limit
        self.notice_limit = notice_limit
        self._notices = 0
        self.dropped_chunks = 0
        self.dropped_notices = 0

    def put(self, msg: ServerMessage) -> None:
        with self._cond:
            if self._closed:
                return
            self._items.append(msg)
            if not isinstance(msg, ChunkOut):
                self._notices += 1
                if self._notices > self.notice_limit and self._drop_oldest(lambda m: not isinstance(m, ChunkOut)):
                    self._notices -= 1
                    self.dropped_notices += 1
            while len(self._items) > self.limit + self._notices and self._drop_oldest(lambda m: isinstance(m, ChunkOut)):
                self.dropped_chunks += 1
            self._cond.notify()

    def _drop_oldest(self, matches: Callable[[ServerMessage], bool]) -> bool:
        for k, old in enumerate(self._items):
            if matches(old):
                del self._items[k]
                return True
        return False

    def get(self, timeout: float | None = None) -> ServerMessage | None:
        with self._cond:
            while not self._items and not self._closed:
                if not self._cond.wait(timeout):
                    return None
            if not self._items:
                return None
            msg = self._items.popleft()
            if not isinstance(msg, ChunkOut):
                self._notices -= 1
            return msg

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed
