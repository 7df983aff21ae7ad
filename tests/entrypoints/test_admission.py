"""Admission on the entrypoints: a slot is held by a robot that asks, not by a socket or a
registration, and one host cannot register faster than its limit, on gRPC and openpi alike."""

from __future__ import annotations

import contextlib
import socket
import threading
import time

import grpc
import numpy as np
import pytest
from websockets.sync.client import connect

from lerobot_armory.engine.options import EngineOptions, PolicyOptions
from lerobot_armory.entrypoints.openpi import endpoint as openpi_endpoint
from lerobot_armory.entrypoints.openpi.codec import pack, unpack
from lerobot_armory.entrypoints.server import build_server
from lerobot_armory.robot.connection import Connection
from lerobot_armory.schedulers import EarliestDeadlineConfig
from lerobot_armory.serving.admission import AdmissionLimiter
from lerobot_armory.serving.config import OpenpiOptions, ServerConfig
from tests.support import adversaries as adv
from tests.support.cluster import make_planner
from tests.support.pusher import wait_for

OBS = {"observation/image": np.zeros((32, 32, 3), np.uint8), "observation/state": np.zeros(2)}


@pytest.fixture(scope="module")
def small_server(tmp_path_factory):
    """The real server with room for 3 robots and an openpi port."""
    planner = make_planner(tmp_path_factory.mktemp("planner") / "planner")
    cfg = ServerConfig(
        policy=PolicyOptions(planner, "cpu"), engine=EngineOptions(emulate_profile="h100-pi05"),
        scheduler=EarliestDeadlineConfig(), max_batch_size=2, max_robots=3, status_interval_s=0.0, log_level="warning",
        port=0, openpi=OpenpiOptions(port=0),
    )  # fmt: skip
    server, _ = build_server(cfg)
    yield server
    server.stop()


def _openpi_sessions(server) -> int:
    with server.fleet.cond:
        return sum(s.robot_id.startswith("openpi-") for s in server.fleet.sessions.values())


def test_openpi_connections_that_never_ask_hold_no_slot(small_server):
    url = f"ws://127.0.0.1:{small_server.openpi.port}"
    with contextlib.ExitStack() as stack:
        idle = [stack.enter_context(connect(url, compression=None, max_size=None)) for _ in range(8)]  # more than the fleet holds
        for ws in idle:
            unpack(ws.recv(timeout=10), 1 << 20)  # the metadata: they are connected
        assert _openpi_sessions(small_server) == 0
        # A gRPC robot and an openpi client that asks are both served.
        conn = Connection(small_server.address)
        try:
            conn.register("grpc-robot", {"observation.state": ("float32", (2,)), "observation.images.front": ("uint8", (32, 32, 3))},
                          fps=20, h_min=1, h_max=5)  # fmt: skip
        finally:
            conn.close()
        with connect(url, compression=None, max_size=None) as asker:
            unpack(asker.recv(timeout=10), 1 << 20)
            asker.send(pack(OBS))
            assert unpack(asker.recv(timeout=10), 1 << 20)["actions"].shape == (10, 2)
            assert _openpi_sessions(small_server) == 1


def test_a_connection_that_does_not_ask_in_time_is_closed_and_waiting_ones_are_capped(small_server, monkeypatch):
    monkeypatch.setattr(openpi_endpoint, "FIRST_REQUEST_S", 0.5)
    monkeypatch.setattr(openpi_endpoint, "MAX_WAITING", 2)
    url = f"ws://127.0.0.1:{small_server.openpi.port}"
    with contextlib.ExitStack() as stack:
        waiting = [stack.enter_context(connect(url, compression=None, max_size=None)) for _ in range(2)]
        for ws in waiting:
            unpack(ws.recv(timeout=10), 1 << 20)
        with connect(url, compression=None, max_size=None) as third:
            assert "already waiting for their first request" in third.recv(timeout=10)
        for ws in waiting:
            assert "no request within 0.5 s" in ws.recv(timeout=10)
        assert wait_for(lambda: small_server.openpi.waiting == 0, timeout=5)
        assert small_server.openpi.refused["waiting"] >= 1 and small_server.openpi.refused["idle"] >= 2


def test_one_host_cannot_register_faster_than_its_limit_on_grpc_or_openpi(small_server):
    limiter = AdmissionLimiter(peer_rate_hz=0.01, peer_burst=4)
    assert small_server.service.registrar is small_server.openpi.registrar is small_server.registrar
    old = small_server.registrar.admission
    small_server.registrar.admission = limiter  # gRPC and openpi register through one registrar
    features = {"observation.state": ("float32", (2,)), "observation.images.front": ("uint8", (32, 32, 3))}
    try:
        codes = []
        for k in range(6):
            conn = Connection(small_server.address)
            try:
                conn.register(f"flood-{k}", features, fps=20, h_min=1, h_max=5)
                codes.append("OK")
            except grpc.RpcError as exc:
                codes.append(exc.code().name)
                assert "too many registrations from this host (127.0.0.1)" in exc.details()
            finally:
                conn.close()
        assert codes == ["OK"] * 4 + ["RESOURCE_EXHAUSTED"] * 2
        with connect(f"ws://127.0.0.1:{small_server.openpi.port}", compression=None, max_size=None) as ws:
            unpack(ws.recv(timeout=10), 1 << 20)
            ws.send(pack(OBS))  # its first request registers it: the same host's bucket is empty
            assert "too many registrations from this host" in ws.recv(timeout=10)
    finally:
        small_server.registrar.admission = old


@pytest.mark.slow
def test_openpi_clients_that_never_read_their_replies_are_served_as_any_client_and_hurt_nobody(small_server):
    """benchmarks/adversarial.py's openpi_never_reads attacker (valid requests as fast as the server
    takes them, replies never read) beside an openpi client that reads: the attacker's requests
    are valid observations served as a client's, and the reading client keeps being served."""
    features = {"observation.state": ("float32", (2,)), "observation.images.front": ("uint8", (32, 32, 3))}
    stop = threading.Event()
    attack, honest = adv.AttackReport("openpi_never_reads"), adv.AttackReport("openpi_honest")
    kwargs = {"port": small_server.openpi.port}
    threads = [
        threading.Thread(target=adv.openpi_never_reads, args=(small_server.address, stop, features, attack), kwargs={**kwargs, "connections": 2}),
        threading.Thread(target=adv.openpi_honest, args=(small_server.address, stop, features, honest), kwargs={**kwargs, "connections": 1}),
    ]
    for t in threads:
        t.start()
    try:
        time.sleep(3.0)
        with small_server.fleet.cond:
            sessions = [(s.counters.chunks_sent, s.counters.rejected) for s in small_server.fleet.sessions.values() if s.robot_id.startswith("openpi-")]
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=15)
    assert not any(t.is_alive() for t in threads)
    assert honest.counts["chunks"] >= 5 and not honest.counts["refusals"], honest.summary()
    assert len(sessions) == 3 and all(sent > 0 and rejected == 0 for sent, rejected in sessions), sessions
    # It sent far more than was answered: the rest waits in the server's bounded queues and the kernel's.
    assert attack.counts["requests sent"] > sum(sent for sent, _ in sessions), attack.summary()
    assert small_server.loop.alive and small_server.loop.stats.failed_batches == 0
    assert wait_for(lambda: _openpi_sessions(small_server) == 0, timeout=10)  # all left with their sockets


def test_an_openpi_client_that_takes_none_of_its_replies_is_dropped(small_server, monkeypatch):
    """Replies that are never read fill the socket until the server's send waits, and websockets'
    keepalive ping waits behind them: without a bound the connection (and its handler) would stay
    forever. Text frames are answered at once, so a raw client with a 4 KiB window that sends them
    and never reads gets there in well under a second."""
    monkeypatch.setattr(openpi_endpoint, "SEND_TIMEOUT_S", 0.5)
    before = small_server.openpi.refused["unread"]
    port = small_server.openpi.port
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.settimeout(0.2)
    s.connect(("127.0.0.1", port))
    s.sendall(adv._ws_upgrade("127.0.0.1", port))
    assert b" 101 " in s.recv(4096)
    frame = adv._ws_frame(b"not a request, and nobody reads the answer", opcode=1)
    dropped, deadline = False, time.monotonic() + 15
    try:
        while not dropped and time.monotonic() < deadline:
            try:
                s.send(frame)
            except TimeoutError:
                pass  # the server stopped reading: its replies wait
            except OSError:
                dropped = True
    finally:
        s.close()
    assert dropped, "the server kept a connection that reads nothing"
    assert small_server.openpi.refused["unread"] == before + 1
    assert wait_for(lambda: _openpi_sessions(small_server) == 0, timeout=10)
    with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:  # nobody else noticed
        unpack(ws.recv(timeout=10), 1 << 20)
        ws.send(pack(OBS))
        assert unpack(ws.recv(timeout=10), 1 << 20)["actions"].shape == (10, 2)
