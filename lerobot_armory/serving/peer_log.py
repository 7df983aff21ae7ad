"""Per-peer log throttling: a robot that misbehaves on every message gets one log line per interval.

A robot sending garbage 100 times a second must not write 100 warnings a second (nor a traceback
each): the log would drown the fleet's other lines and fill the disk. :class:`ThrottledLog` lets
the first warning about a peer through, counts the ones that follow within ``interval_s`` and
reports that count on the peer's next line. Its memory is bounded: peers quiet for ``forget_s``
are forgotten and the table never holds more than ``max_peers`` of them (the longest quiet go first),
so a flood of one-message peers (every new connection is a new ``host:port``) cannot grow it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

DEFAULT_INTERVAL_S = 10.0
DEFAULT_MAX_PEERS = 4096

_default_log = logging.getLogger("lerobot_armory.server.peers")


@dataclass
class _Peer:
    logged_at: float  # when this peer's last line was written
    seen_at: float  # when a warning about it last came in (written or not)
    suppressed: int = 0  # warnings not written since logged_at


class ThrottledLog:
    """At most one warning line per peer per ``interval_s``; no tracebacks. Thread-safe.

    Args:
        logger: where lines go (``lerobot_armory.server.peers`` by default).
        interval_s: least time between two lines about the same peer.
        forget_s: a peer with no warning for this long is dropped from the table (default
            ``6 * interval_s``); must be >= ``interval_s`` or throttling would not hold.
        max_peers: table size cap; beyond it the peer quiet for longest is dropped.
        clock: seconds, non-decreasing (tests inject a fake one).
    """

    def __init__(
        self,
        logger: logging.Logger | None = None,
        interval_s: float = DEFAULT_INTERVAL_S,
        forget_s: float | None = None,
        max_peers: int = DEFAULT_MAX_PEERS,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        forget_s = 6 * interval_s if forget_s is None else forget_s
        if interval_s < 0 or forget_s < interval_s or max_peers < 1:
            raise ValueError(
                f"need 0 <= interval_s <= forget_s and max_peers >= 1, got {interval_s}, {forget_s}, {max_peers}"
            )
        self.logger = logger or _default_log
        self.interval_s = interval_s
        self.forget_s = forget_s
        self.max_peers = max_peers
        self.clock = clock
        self.suppressed_total = 0  # every line ever held back, including counts lost with forgotten peers
        self._peers: OrderedDict[str, _Peer] = OrderedDict()  # oldest seen_at first
        self._lock = threading.Lock()

    def __len__(self) -> int:
        """Peers currently remembered."""
        return len(self._peers)

    def warn(self, peer: str, message: str) -> bool:
        """Log ``message`` about ``peer`` unless a line about it went out within ``interval_s``.

        Returns:
            True if a line was written; False if it was counted as suppressed.
        """
        now = self.clock()
        with self._lock:
            self._forget(now)
            suppressed = self._note(peer, now)
        if suppressed is None:
            return False
        # outside the lock: a slow log handler must not serialise every reader thread behind it
        suffix = f" ({suppressed} more suppressed)" if suppressed else ""
        self.logger.warning("%s: %s%s", peer, message, suffix)
        return True

    def _note(self, peer: str, now: float) -> int | None:
        """Record a warning; the count of lines held back since the last one if it is written, else None."""
        state = self._peers.pop(peer, None)
        if state is not None and now - state.logged_at < self.interval_s:
            state.suppressed += 1
            state.seen_at = now
            self.suppressed_total += 1
            self._peers[peer] = state  # re-inserted last: most recently seen
            return None
        self._peers[peer] = _Peer(logged_at=now, seen_at=now)
        while len(self._peers) > self.max_peers:
            self._peers.popitem(last=False)
        return 0 if state is None else state.suppressed

    def _forget(self, now: float) -> None:
        """Drop peers not seen for ``forget_s`` (they sit at the front: the table is in seen_at order)."""
        while self._peers:
            oldest = next(iter(self._peers.values()))
            if now - oldest.seen_at < self.forget_s:
                return
            self._peers.popitem(last=False)
