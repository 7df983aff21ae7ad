"""``--openpi.port``: openpi's websocket policy protocol, served by the same fleet, mirrors and scheduler.

An unchanged ``openpi_client.websocket_client_policy.WebsocketClientPolicy`` connects; the server
speaks first with its metadata; then each ``infer(obs)`` is one binary msgpack frame in and one
out (``{"actions": (H, A) float32, "server_timing": {...}}``), as openpi's own server does. A
message that does not decode or fit the policy gets a *text* frame saying why (openpi's client
raises it as ``RuntimeError``) and the connection stays open; no other robot notices.

Each connection that asks is a robot of the fleet: it is registered with its first request (a
connection that never asks holds no slot, and is closed after ``FIRST_REQUEST_S``), under the
same admission limits as gRPC registrations. openpi's client asks when it needs a chunk and waits, so
the mirror models it as a robot whose request is due now: it executes ``--openpi.replan_steps``
actions per chunk (``h_max``) at ``--openpi.fps``, its clock is the server's (zero offset), and
every request after the first comes with the receipt of the chunk before (executed from its
start). Its observations enter the same :class:`Fleet` as the gRPC robots', so openpi and gRPC
robots share batches under any scheduler.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import itertools
import logging
import threading
import time
from collections.abc import AsyncIterator
from http import HTTPStatus
from typing import Any

from lerobot_armory.errors import ConfigError
from lerobot_armory.serving.fleet import Fleet, FleetError
from lerobot_armory.serving.session import RobotSession
from lerobot_armory.serving.grant_rules import GrantRequest, GrantRules
from lerobot_armory.serving.registration import Registrar, Registration
from lerobot_armory.serving.messages import ChunkOut, ClockSync, ExecutionReport, Notice, NoticeKind, Receipt
from lerobot_armory.entrypoints.openpi.keymap import KeyMap
from lerobot_armory.entrypoints.openpi.codec import pack, unpack
from lerobot_armory.serving.config import OpenpiOptions
from lerobot_armory.serving.admission import AdmissionLimiter
from lerobot_armory.serving.security import Credential
from lerobot_armory.feature_spec import WireError

log = logging.getLogger(__name__)

CHUNK_TIMEOUT_S = 30.0  # a chunk not served in this long is an error frame, not a hang
# A connection becomes a robot of the fleet (takes a slot) with its first request, not when it
# opens: one that sends none within FIRST_REQUEST_S is closed, and at most MAX_WAITING connections
# wait for their first request at once (more are refused at once, so idle sockets cannot pile up).
# openpi's client sends its first observation as soon as its policy runs.
FIRST_REQUEST_S = 10.0
MAX_WAITING = 64
# Longest a request is held for the progress bound (replan actions at the lowest sane fps).
MAX_PACE_S = 10.0
# A client that takes none of our bytes for this long while a reply waits is dropped: its replies
# would wait forever (websockets' keepalive ping waits behind them and never times out).
SEND_TIMEOUT_S = 10.0
# A connection must finish its TLS handshake, then its HTTP upgrade, each within this long
# (websockets' default, named here): a client that opens a socket and stalls holds it no longer.
OPEN_TIMEOUT_S = 10.0


class OpenpiSession:
    """One openpi connection as a robot of the fleet (blocking calls; run off the event loop)."""

    def __init__(self, fleet: Fleet, session: RobotSession, keymap: KeyMap, replan_steps: int) -> None:
        self.fleet = fleet
        self.session = session
        self.keymap = keymap
        self.replan = replan_steps
        self.index = 0
        self.last_chunk: tuple[int, float] | None = None  # (chunk_id, sent time) of the chunk before
        self.executed = 0
        self.last_total_s: float | None = None

    def infer(self, obs: Any) -> dict[str, Any]:
        """One request: the observation in, the chunk out (WireError / RuntimeError on failure)."""
        start = time.perf_counter()
        arrays, task = self.keymap.apply(obs)
        self._pace()
        now = self.fleet.clock()
        if self.last_chunk is not None:
            chunk_id, sent = self.last_chunk
            self.executed += self.replan
            report = ExecutionReport(now, self.index, self.executed, 0, (Receipt(chunk_id, sent, 0),))
            self.fleet.on_report(self.session, report, now)
        self.session.task = task or self.session.task
        # A chunk that came after its request timed out answers an older observation: never
        # hand it to this one.
        while self.session.outbox.get(timeout=0) is not None:
            pass
        try:
            self.fleet.on_observation(self.session, self.index, now, arrays, now)
        except ValueError as exc:
            raise WireError(str(exc)) from None
        deadline = time.monotonic() + CHUNK_TIMEOUT_S
        while True:
            msg = self.session.outbox.get(timeout=max(0.0, deadline - time.monotonic()))
            if msg is None:
                raise RuntimeError("no chunk: " + ("the server dropped this client" if self.session.outbox.closed else "timed out"))
            if isinstance(msg, ChunkOut):
                break
            if isinstance(msg, Notice) and msg.kind in (NoticeKind.INFERENCE_FAILED, NoticeKind.DROPPED, NoticeKind.SHUTDOWN):
                raise RuntimeError(msg.message)
        chunk = msg
        actions = chunk.actions  # the loop's own array: never encoded, never decoded again
        sent = self.fleet.clock()
        self.last_chunk = (chunk.chunk_id, sent)
        self.index = chunk.i_start + self.replan  # what it will have executed when it asks again
        total = time.perf_counter() - start
        timing = {"infer_ms": total * 1000.0}
        if self.last_total_s is not None:
            timing["prev_total_ms"] = self.last_total_s * 1000.0
        self.last_total_s = total
        return {"actions": actions, "server_timing": timing}


    def _pace(self) -> None:
        """Hold a request that comes sooner than ``replan`` actions at ``--openpi.fps`` after its
        chunk left the server (a simulation faster than real time, or a client asking in a loop):
        the index it stands for is the mirror's progress bound's to allow, as for any robot, and a
        client cannot buy chunks by asking faster."""
        with self.fleet.cond:
            wait = self.session.mirror.progress_wait_s(self.index, self.fleet.clock())
        if 0.0 < wait <= MAX_PACE_S:
            time.sleep(wait)


class OpenpiEndpoint:
    """The websocket server (its own thread and event loop) in front of a :class:`Fleet`."""

    def __init__(
        self,
        fleet: Fleet,
        keymap: KeyMap,
        options: OpenpiOptions,
        chunk_size: int,
        metadata: dict[str, Any],
        host: str = "127.0.0.1",
        max_message_bytes: int = 16 << 20,
        registrar: Registrar | None = None,
        tls: tuple[bytes, bytes] | None = None,
        policy_name: str | None = None,
    ) -> None:
        self.fleet = fleet
        # The policy openpi clients are served by (they cannot name one): the server's first.
        self.policy_name = policy_name
        # Credentials, admission and grants: the one registration path, shared with gRPC.
        self.registrar = registrar or Registrar(fleet, GrantRules.builtin(), AdmissionLimiter())
        self.waiting = 0  # connections open that have not asked yet (the event loop's thread only)
        self.refused = collections.Counter()  # why connections were refused, by reason
        self.keymap = keymap
        self.options = options
        self.chunk_size = chunk_size
        self.metadata = metadata
        self.host = host
        self.max_message_bytes = max_message_bytes
        self.tls = tls
        self._ids = itertools.count()
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._server: Any = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="armory-openpi", daemon=True)
        self.port = 0

    def start(self) -> OpenpiEndpoint:
        self._thread.start()
        self._ready.wait(30)
        if self._error is not None:
            raise ConfigError("openpi.port", f"cannot serve on {self.host}:{self.options.port}: {self._error}")
        return self

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._serve())
        except BaseException as exc:  # noqa: BLE001 - reported by start()
            self._error = exc
            self._ready.set()
            return
        self._loop.run_forever()

    async def _serve(self) -> None:
        from websockets.asyncio.server import serve

        def health(connection: Any, request: Any) -> Any:
            if request.path == "/healthz":  # openpi's health check
                return connection.respond(HTTPStatus.OK, "OK\n")
            return None

        self._server = await serve(
            self._handle, self.host, self.options.port or 0, compression=None, max_size=self.max_message_bytes,
            process_request=health, ssl=self._ssl_context(), open_timeout=OPEN_TIMEOUT_S,
            # A client that sends without waiting for replies queues at most this many frames
            # here (each up to max_size): openpi's client sends one and waits.
            max_queue=4,
        )  # fmt: skip
        self.port = self._server.sockets[0].getsockname()[1]
        self._ready.set()

    def _ssl_context(self) -> Any:
        """wss:// with the gRPC port's certificate when the server has one (openpi's client takes
        ``host="wss://..."``); None: plaintext ws://."""
        if self.tls is None:
            return None
        import os
        import ssl
        import tempfile

        key, cert = self.tls
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        # ssl loads PEM from files only: private temporary files, removed at once.
        with tempfile.TemporaryDirectory() as tmp:
            paths = [os.path.join(tmp, "cert.pem"), os.path.join(tmp, "key.pem")]
            for path, data in zip(paths, (cert, key), strict=True):
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
                with os.fdopen(fd, "wb") as handle:
                    handle.write(data)
            context.load_cert_chain(paths[0], paths[1])
        return context

    def _authenticate(self, robot_id: str, api_key: str) -> Credential | None:
        """The credential of ``api_key`` (None without auth); FleetError when it is wrong."""
        return self.registrar.authenticate(robot_id, api_key, "api key (openpi client's api_key)")

    def _register(self, robot_id: str, credential: Credential | None, peer: str) -> RobotSession:
        self.registrar.admit(peer, credential)
        opts = self.options
        asked = GrantRequest(robot_id, opts.fps, 1, min(opts.replan_steps, self.chunk_size), 1.0, opts.tier)
        features = {f.name: f for f in self.keymap.features}
        now = self.fleet.clock()
        registration = Registration(asked, self.chunk_size, features, policy=self.policy_name, check_horizon=False)
        session, _ = self.registrar.register(registration, credential, now)
        # Its clock is ours: complete the registration exchange with zero offset and no delay.
        assert session.clock.register_stamps is not None
        b, s = session.clock.register_stamps
        self.fleet.on_clock_sync(session, ClockSync(0, client_send_time=b, client_recv_time=s), now)
        self.fleet.attach(session.session_id, credential.digest if credential else None)
        return session

    async def _refuse(self, websocket: Any, reason: str, why: str) -> None:
        self.refused[why] += 1
        with contextlib.suppress(ConnectionAbortedError):  # it reads nothing: already dropped
            await self._send(websocket, f"lerobot-armory refused this client: {reason}")
            await websocket.close()

    async def _send(self, websocket: Any, message: str | bytes) -> None:
        """Send one frame; a client that does not read it within ``SEND_TIMEOUT_S`` is dropped
        (counted in ``refused["unread"]``) and ConnectionAbortedError ends its handler."""
        try:
            await asyncio.wait_for(websocket.send(message), SEND_TIMEOUT_S)
        except TimeoutError:
            self.refused["unread"] += 1
            log.info("openpi client %s read nothing for %g s: dropped", websocket.remote_address, SEND_TIMEOUT_S)
            websocket.transport.abort()
            raise ConnectionAbortedError(f"the client read no reply for {SEND_TIMEOUT_S:g} s") from None

    async def _handle(self, websocket: Any) -> None:
        header = websocket.request.headers.get("Authorization", "") if websocket.request is not None else ""
        # openpi's client sends "Api-Key <key>"; the key is compared as sent (HTTP itself drops
        # the whitespace around a header's value, so no client can send a padded key).
        api_key = header[len("Api-Key ") :] if header.startswith("Api-Key ") else ""
        address = websocket.remote_address
        peer = str(address[0]) if isinstance(address, tuple) and address else str(address)
        robot_id = f"openpi-{next(self._ids)}"
        try:
            credential = self._authenticate(robot_id, api_key)
        except FleetError as exc:
            await self._refuse(websocket, str(exc), "unauthenticated")
            return
        if self.waiting >= MAX_WAITING:
            await self._refuse(
                websocket, f"{MAX_WAITING} connections are already waiting for their first request; retry later", "waiting"
            )
            return
        self.waiting += 1
        try:
            await self._send(websocket, pack(self.metadata))
            first = await asyncio.wait_for(websocket.recv(), FIRST_REQUEST_S)
        except TimeoutError:
            await self._refuse(websocket, f"no request within {FIRST_REQUEST_S:g} s (a connection holds a slot only while it asks)", "idle")
            return
        except Exception:  # noqa: BLE001 - closed before asking: nothing was registered
            return
        finally:
            self.waiting -= 1
        session: RobotSession | None = None
        frames = _prepend(first, websocket)
        try:
            async for frame in frames:
                if session is None or self.fleet.sessions.get(session.session_id) is not session:
                    # The first request, or the first after the fleet gave an idle client's slot away.
                    try:
                        session = await asyncio.to_thread(self._register, robot_id, credential, peer)
                    except FleetError as exc:
                        await self._refuse(websocket, str(exc), exc.code.lower())
                        return
                    client = OpenpiSession(self.fleet, session, self.keymap, min(self.options.replan_steps, self.chunk_size))
                    log.info("openpi client %s asks as %s", address, session.robot_id)
                if isinstance(frame, str):
                    await self._send(websocket, "expected a binary msgpack frame (openpi's client packs the observation), got text")
                    continue
                try:
                    obs = unpack(frame, self.max_message_bytes)
                    reply = await asyncio.to_thread(client.infer, obs)
                except (WireError, RuntimeError) as exc:
                    session.counters.rejected += 1
                    await self._send(websocket, f"lerobot-armory: request refused: {exc}")
                    continue
                await self._send(websocket, pack(reply))
        except Exception as exc:  # noqa: BLE001 - a connection's failure is its own
            log.info("openpi client %s: connection ended (%s)", robot_id, type(exc).__name__)
        finally:
            if session is not None:
                await asyncio.to_thread(self.fleet.detach, session.session_id)
                log.info("openpi client %s disconnected", session.robot_id)
            # Closed here: a connection that ended in the middle of a reply (a client that never
            # reads, then drops) must not leave its frame generator to a later collection.
            with contextlib.suppress(Exception):
                await frames.aclose()

    def stop(self) -> None:
        if self._server is None:
            return

        async def close() -> None:
            self._server.close()
            await self._server.wait_closed()

        asyncio.run_coroutine_threadsafe(close(), self._loop).result(timeout=10)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=10)


async def _prepend(first: Any, websocket: Any) -> AsyncIterator[Any]:
    """The first frame (already received), then the connection's next ones until it closes."""
    yield first
    async for frame in websocket:
        yield frame
