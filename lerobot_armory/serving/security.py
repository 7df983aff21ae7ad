"""Authentication tokens, TLS material and per-robot rate limits.

Tokens come from ``--auth_token_file``: one token per line is a fleet token any robot may use;
``@NAME TOKEN`` is a fleet token with a name (the grant rules can give it its own rule);
``ROBOT_ID TOKEN`` binds a token to one robot id, and that id is then *only* reachable with its own
token (a fleet token cannot register it). Blank lines and ``#`` comments are ignored.
Comparisons are constant-time; tokens are never logged.
"""

from __future__ import annotations

import hashlib
import hmac
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from lerobot_armory.errors import ConfigError


@dataclass(frozen=True)
class Credential:
    """Who a token proved to be: ``name`` is ``robot:ID``, ``token:NAME`` or ``fleet``; ``group``
    names a grant rules token rule (``@NAME`` lines) or is None; ``digest`` binds a session to
    the token that registered it without keeping the token."""

    name: str
    group: str | None
    digest: bytes


def token_digest(token: str) -> bytes:
    return hashlib.sha256(token.encode()).digest()


@dataclass
class AuthTokens:
    """Fleet-wide (optionally named) and per-robot tokens."""

    fleet: list[str] = field(default_factory=list)
    per_robot: dict[str, str] = field(default_factory=dict)
    named: dict[str, str] = field(default_factory=dict)  # name -> fleet token

    @classmethod
    def load(cls, path: str, field_name: str = "auth_token_file") -> AuthTokens:
        try:
            text = Path(path).read_text()
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(field_name, f"cannot read {path}: {exc}") from None
        tokens = cls()
        for n, raw in enumerate(text.splitlines(), start=1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            parts = line.split()
            if len(parts) == 1:
                tokens.fleet.append(parts[0])
            elif len(parts) == 2 and parts[0].startswith("@") and len(parts[0]) > 1:
                tokens.named[parts[0][1:]] = parts[1]
            elif len(parts) == 2:
                tokens.per_robot[parts[0]] = parts[1]
            else:
                raise ConfigError(field_name, f"{path}:{n}: expected 'TOKEN', '@NAME TOKEN' or 'ROBOT_ID TOKEN'")
        if not tokens.fleet and not tokens.per_robot and not tokens.named:
            raise ConfigError(field_name, f"{path} holds no token")
        for t in [*tokens.fleet, *tokens.per_robot.values(), *tokens.named.values()]:
            if len(t) < 16:
                raise ConfigError(field_name, f"{path}: tokens must be at least 16 characters")
        return tokens

    def identify(self, robot_id: str, token: str) -> Credential | None:
        """The credential ``token`` proves for ``robot_id``, or None (constant-time comparisons).

        An id with its own token accepts only that token: a fleet token cannot take it.
        """
        given = token.encode()
        bound = self.per_robot.get(robot_id)
        if bound is not None:
            ok = hmac.compare_digest(bound.encode(), given)
            return Credential(f"robot:{robot_id}", None, token_digest(token)) if ok else None
        found: Credential | None = None
        for t in self.fleet:
            if hmac.compare_digest(t.encode(), given):
                found = Credential("fleet", None, token_digest(token))
        for name, t in self.named.items():
            if hmac.compare_digest(t.encode(), given):
                found = Credential(f"token:{name}", name, token_digest(token))
        return found

    def check(self, robot_id: str, token: str) -> bool:
        """True if ``token`` is valid for ``robot_id`` (see :meth:`identify`)."""
        return self.identify(robot_id, token) is not None


@dataclass
class OperatorTokens:
    """``--operator_token_file``: the tokens that may call the admin RPCs (swap a policy, status).

    One token per line (blank lines and ``#`` comments ignored), at least 16 characters, none of
    them a robot token: an operator token is a separate secret, and a robot's token never
    authorises an admin call. Comparisons are constant-time; tokens are never logged.
    """

    tokens: list[str] = field(default_factory=list)

    @classmethod
    def load(cls, path: str, robots: AuthTokens | None = None, field_name: str = "operator_token_file") -> OperatorTokens:
        try:
            text = Path(path).read_text()
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(field_name, f"cannot read {path}: {exc}") from None
        tokens = []
        for n, raw in enumerate(text.splitlines(), start=1):
            line = raw.split("#", 1)[0].strip()
            if not line:
                continue
            if len(line.split()) != 1:
                raise ConfigError(field_name, f"{path}:{n}: expected one token per line")
            if len(line) < 16:
                raise ConfigError(field_name, f"{path}: tokens must be at least 16 characters")
            tokens.append(line)
        if not tokens:
            raise ConfigError(field_name, f"{path} holds no token")
        if robots is not None:
            robot_tokens = {*robots.fleet, *robots.per_robot.values(), *robots.named.values()}
            if any(t in robot_tokens for t in tokens):
                raise ConfigError(field_name, f"{path} holds a token of --auth_token_file: operator tokens must differ from robot tokens")
        return cls(tokens)

    def check(self, token: str) -> bool:
        """True if ``token`` is an operator token (every token compared, in constant time each)."""
        given = token.encode()
        found = False
        for t in self.tokens:
            found |= hmac.compare_digest(t.encode(), given)
        return found and bool(token)


def read_tls(cert: str | None, key: str | None) -> tuple[bytes, bytes] | None:
    """(key, certificate chain) PEM bytes for the server, or None without TLS."""
    if not cert and not key:
        return None
    if not (cert and key):
        raise ConfigError("tls_cert", "TLS needs both --tls_cert and --tls_key")
    try:
        return Path(key).read_bytes(), Path(cert).read_bytes()
    except OSError as exc:
        raise ConfigError("tls_cert", f"cannot read the TLS files: {exc}") from None


class RateLimiter:
    """Token bucket: ``rate_hz`` sustained, bursts up to ``burst`` messages."""

    def __init__(self, rate_hz: float, burst: float | None = None, clock=time.monotonic) -> None:
        self.rate = rate_hz
        self.capacity = burst if burst is not None else max(10.0, rate_hz)
        self.tokens = self.capacity
        self.clock = clock
        self.updated = clock()
        self._lock = threading.Lock()

    def allow(self) -> bool:
        with self._lock:
            now = self.clock()
            self.tokens = min(self.capacity, self.tokens + (now - self.updated) * self.rate)
            self.updated = now
            if self.tokens >= 1.0:
                self.tokens -= 1.0
                return True
            return False
