"""Admission: how fast one peer, or one credential, may register robots.

Registering costs the server a session, a mirror and a slot until the registration expires
(``Fleet``'s ``stale_session_s``), so a peer that registers thousands of fresh ids a second can
keep honest newcomers out even though each of its registrations is evicted first. Every
entrypoint (gRPC ``Register``, an openpi connection's first request, the cluster front) asks
:meth:`AdmissionLimiter.check` before it registers: a token bucket per peer host and one per
credential. The defaults let a whole fleet restart at once from one host (a burst of 256, then 32
a second) and stop a flood: 3,000 registrations in 4 s from one host get 256 + ~128 through.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable

from lerobot_armory.serving.security import RateLimiter

PEER_RATE_HZ = 32.0
PEER_BURST = 256.0
CREDENTIAL_RATE_HZ = 64.0
CREDENTIAL_BURST = 512.0
# Buckets kept (least recently used dropped first): memory stays bounded however many peers come.
MAX_KEYS = 4096


class AdmissionLimiter:
    """Token buckets per peer host and per credential digest, in bounded memory."""

    def __init__(
        self,
        peer_rate_hz: float = PEER_RATE_HZ,
        peer_burst: float = PEER_BURST,
        credential_rate_hz: float = CREDENTIAL_RATE_HZ,
        credential_burst: float = CREDENTIAL_BURST,
        max_keys: int = MAX_KEYS,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._limits = {"peer": (peer_rate_hz, peer_burst), "credential": (credential_rate_hz, credential_burst)}
        self._buckets: collections.OrderedDict[tuple[str, str | bytes], RateLimiter] = collections.OrderedDict()
        self._max_keys = max_keys
        self._clock = clock
        self._lock = threading.Lock()
        self.refused = 0

    def check(self, peer: str, credential: bytes | None = None) -> str | None:
        """Why a registration from ``peer`` (a host, no port) with ``credential`` is refused now,
        or None: admitted (and counted)."""
        keys: list[tuple[str, str | bytes]] = [("peer", peer)]
        if credential is not None:
            keys.append(("credential", credential))
        with self._lock:
            for kind, key in keys:
                if not self._bucket(kind, key).allow():
                    self.refused += 1
                    rate, _ = self._limits[kind]
                    who = f"this host ({peer})" if kind == "peer" else "this credential"
                    return f"too many registrations from {who}: at most {rate:g} a second after a burst; retry later"
        return None

    def _bucket(self, kind: str, key: str | bytes) -> RateLimiter:
        bucket = self._buckets.get((kind, key))
        if bucket is None:
            rate, burst = self._limits[kind]
            bucket = self._buckets[(kind, key)] = RateLimiter(rate, burst, clock=self._clock)
            while len(self._buckets) > self._max_keys:
                self._buckets.popitem(last=False)
        else:
            self._buckets.move_to_end((kind, key))
        return bucket


def peer_host(peer: str) -> str:
    """The host of a gRPC peer string (``ipv4:1.2.3.4:5678``, ``ipv6:[::1]:5678``) or of an
    address tuple's first element: the part a registration limit keys on (ports change freely)."""
    if peer.startswith("ipv6:["):
        return peer[len("ipv6:") :].split("]")[0] + "]"
    if peer.startswith(("ipv4:", "ipv6:")):
        return peer.split(":", 1)[1].rsplit(":", 1)[0]
    return peer
