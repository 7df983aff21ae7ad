"""Forwarded registrations: the cluster front vouches for the robot's host, and nobody else can.

A replica limits registrations per peer host (:mod:`.admission`). In a cluster every registration
reaches a replica from the front's host, so without more the replicas' per-host limit would be one
bucket for every robot registering through the front: a flood from many addresses, each let
through by the front's own per-host limit, would spend it and keep honest newcomers out.

So the front names the robot's host with each registration it forwards, and proves it: an
HMAC-SHA256, under a key only the front and its replicas hold, over the host and the robot id. A
replica that holds the key counts the registration against the named host when the proof checks
(compared in constant time), and against its real peer otherwise, as a single server does: a robot
that names a host of its own choosing gains nothing.

The key is made by the front when it starts and handed to each replica over the cluster's control
plane (Ray's actor calls, or the process itself), never over the robots' network: only proofs
travel there. A proof binds one host to one robot id, so one captured on an unencrypted link can
only register that robot id again, against that host's budget (that link carries robots' tokens
too: use TLS).
The key never appears in a log line, a metric or an error message; :class:`ForwardingKey`'s
``repr`` hides it.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets

KEY_BYTES = 32
# What the MAC covers is tagged so that it is never mistaken for a MAC over anything else.
_DOMAIN = b"lerobot-armory forwarded-for v1\0"


class ForwardingKey:
    """The secret a front shares with its replicas, and the proofs made with it."""

    __slots__ = ("_secret",)

    def __init__(self, secret: bytes) -> None:
        if len(secret) < 16:
            raise ValueError("a forwarding key needs at least 16 bytes")
        self._secret = bytes(secret)

    @classmethod
    def generate(cls) -> ForwardingKey:
        """A fresh random key (one per front)."""
        return cls(secrets.token_bytes(KEY_BYTES))

    def proof(self, host: str, robot_id: str) -> str:
        """The proof (hex, fit for gRPC metadata) that the front forwards ``robot_id``'s registration from ``host``."""
        host_b, robot_b = host.encode("utf-8", "surrogateescape"), robot_id.encode("utf-8", "surrogateescape")
        message = _DOMAIN + len(host_b).to_bytes(4, "big") + host_b + robot_b
        return hmac.new(self._secret, message, hashlib.sha256).hexdigest()

    def verify(self, host: str, robot_id: str, proof: str) -> bool:
        """Whether ``proof`` is this key's for (``host``, ``robot_id``); constant time in its content."""
        expected = self.proof(host, robot_id).encode("ascii")
        return hmac.compare_digest(expected, proof.encode("utf-8", "surrogateescape"))

    def __repr__(self) -> str:
        return "ForwardingKey(<hidden>)"

    def __reduce__(self) -> tuple[type[ForwardingKey], tuple[bytes]]:
        # Pickled for Ray's actor call that hands it to a replica (slots need this spelled out).
        return (ForwardingKey, (self._secret,))
