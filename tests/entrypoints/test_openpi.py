"""The openpi-compatible endpoint, driven by the real ``openpi-client`` in its own environment.

The clients run in a separate venv with numpy < 2 (``tests/support/openpi_env.py``), as on a robot
computer; they import nothing of ours. The server is the real one (the analytic planner,
batches taking the H100 π0.5 profile's time, EDF, b = 4).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from collections import Counter
from pathlib import Path

import msgpack
import numpy as np
import pytest

from lerobot_armory.schedulers import EarliestDeadlineConfig
from lerobot_armory.entrypoints.server import ServerConfig, build_server
from lerobot_armory.engine.options import EngineOptions
from lerobot_armory.engine.options import PolicyOptions
from lerobot_armory.serving.config import OpenpiOptions
from lerobot_armory.entrypoints.openpi.keymap import KeyMap
from lerobot_armory.entrypoints.openpi.codec import pack, unpack
from lerobot_armory.wire import FeatureSpec, WireError
from tests.support.cluster import make_planner, sim_robot, wait_for
from tests.support.openpi_env import openpi_python

CLIENTS = Path(__file__).resolve().parents[1] / "support" / "openpi_clients.py"


@pytest.fixture(scope="module")
def openpi_env():
    python = openpi_python()
    if python is None:
        pytest.skip("no Python 3.10-3.12 here for openpi-client's numpy<2 environment")
    return python


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    planner = make_planner(tmp_path_factory.mktemp("planner") / "planner")
    cfg = ServerConfig(
        policy=PolicyOptions(planner, "cpu"),
        engine=EngineOptions(emulate_profile="h100-pi05"),
        scheduler=EarliestDeadlineConfig(),
        max_batch_size=4,
        status_interval_s=0.0,
        log_level="warning",
        port=0,
        openpi=OpenpiOptions(port=0),
    )
    server, _ = build_server(cfg)
    yield server
    server.stop()


def run_clients(
    python: str, port: int, out: Path, mode: str, n: int, requests: int, duration_s: float = 0.0, pace_s: float = 0.0
) -> dict:
    args = [python, str(CLIENTS), str(port), str(out), mode, str(n), str(requests), str(duration_s), str(pace_s)]
    done = subprocess.run(args, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads((out / "results.json").read_text())


@pytest.mark.slow
@pytest.mark.subprocess
def test_four_unchanged_openpi_clients_are_served_in_shared_batches_with_the_right_chunks(server, openpi_env, tmp_path):
    first = len(server.batch_log)
    results = run_clients(openpi_env, server.openpi.port, tmp_path, "infer", 4, 25)
    assert sorted(results) == ["0", "1", "2", "3"]
    batches = server.batch_log[first:]
    openpi_sizes = Counter(sum(r.startswith("openpi-") for r in b.robots) for b in batches)
    assert any(size > 1 for size in openpi_sizes), openpi_sizes  # batched, not one at a time
    assert results["0"]["metadata"]["server"] == "lerobot-armory"
    engine = server.loop.engine
    for k in range(4):
        saved = np.load(tmp_path / f"client{k}.npz", allow_pickle=False)
        obs = {"observation.images.front": saved["image"], "observation.state": saved["state"].astype(np.float32)}
        alone = engine.infer([obs], ["reach the target"])[0]
        np.testing.assert_allclose(saved["actions"], alone, rtol=1e-6, atol=1e-6)  # the chunk for that observation


@pytest.mark.subprocess
def test_action_chunk_broker_runs_its_loop(server, openpi_env, tmp_path):
    results = run_clients(openpi_env, server.openpi.port, tmp_path, "broker", 1, 20)
    broker = results["broker"]
    assert broker["server_calls"] == 4  # one round trip per 5 steps
    assert broker["action_shapes"] == [[2]] * 20


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_malformed_request_gets_an_error_frame_and_the_others_continue(server, openpi_env, tmp_path):
    results = run_clients(openpi_env, server.openpi.port, tmp_path, "bad", 4, 20)
    bad = results["bad"]
    assert "not a msgpack message" in bad["errors"][0]
    assert "observation.images.front" in bad["errors"][1] and "[32, 32, 3]" in bad["errors"][1]
    assert bad["then_served"] == [10, 2]
    assert all(len(results[str(k)]["latencies_s"]) == 20 for k in range(3))  # every good request answered


@pytest.mark.slow
@pytest.mark.subprocess
def test_openpi_and_grpc_robots_share_batches(server, openpi_env, tmp_path):
    first = len(server.batch_log)
    robot = sim_robot(f"127.0.0.1:{server.port}", "grpc-robot", fast=False, seed=3)
    # The robot outlives the clients: 20 requests each, paced at replan (5) actions / 20 fps = 0.25 s
    # by the server, or a random 0-0.6 s wait of their own if longer. Without it, clients answered in one batch
    # are released together by the pacing, in a fixed phase with the robot's ticks, and (the robot's
    # batch being shorter than its period) no batch could hold both.
    robot.start(16.0)
    assert wait_for(lambda: any("grpc-robot" in b.robots for b in server.batch_log[first:]), timeout=10)
    run_clients(openpi_env, server.openpi.port, tmp_path, "staggered", 3, 20, pace_s=0.6)
    robot.join()
    mixed = [b for b in server.batch_log[first:] if "grpc-robot" in b.robots and any(r.startswith("openpi-") for r in b.robots)]
    assert mixed, "no batch held both an openpi client and a gRPC robot"


# ---- the wire and the key map, without a client -----------------------------------------------


def frame(obj) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def nd(arr: np.ndarray) -> dict:
    return {b"__ndarray__": True, b"data": arr.tobytes(), b"dtype": arr.dtype.str, b"shape": list(arr.shape)}


@pytest.mark.parametrize(
    ("obj", "why"),
    [
        ({b"__ndarray__": True, b"data": b"x" * 8, b"dtype": "|O", b"shape": [1]}, "not allowed"),
        ({b"__ndarray__": True, b"data": b"x" * 7, b"dtype": "<f4", b"shape": [2]}, "needs 8 bytes"),
        ({b"__ndarray__": True, b"data": b"", b"dtype": "<f4", b"shape": [-1]}, "non-negative"),
        ({b"__ndarray__": True, b"data": b"", b"dtype": "<c8", b"shape": [0]}, "not allowed"),
        ({b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": ">f8", b"shape": [1]}, "big-endian"),
        ({b"__ndarray__": True, b"data": b"", b"dtype": "<f4", b"shape": [0], b"extra": 1}, "exactly the keys"),
        ({b"__npgeneric__": True, b"data": "1", b"dtype": "<i8"}, "must be a number"),
    ],
)
def test_the_decoder_refuses_what_openpi_s_client_would_never_send(obj, why):
    with pytest.raises(WireError, match=why):
        unpack(frame({"x": obj}), 1 << 20)


def test_the_decoder_refuses_extensions_oversize_and_deep_nesting():
    with pytest.raises(WireError, match="ext"):
        unpack(msgpack.packb(msgpack.ExtType(1, b"pickle?")), 1 << 20)
    with pytest.raises(WireError, match="over the limit"):
        unpack(b"\x00" * 100, 50)
    with pytest.raises(WireError):
        unpack(b"\x91" * 100_000 + b"\x01", 1 << 20)  # a list in a list ... 100,000 deep


def test_arrays_round_trip_as_openpi_packs_them():
    obs = {"a": nd(np.arange(6, dtype=np.float32).reshape(2, 3)), "b": {b"__npgeneric__": True, b"data": 3, b"dtype": "<i8"}}
    got = unpack(frame(obs), 1 << 20)
    np.testing.assert_array_equal(got["a"], np.arange(6, dtype=np.float32).reshape(2, 3))
    assert got["b"] == 3 and got["b"].dtype == np.int64
    back = unpack(pack({"actions": got["a"]}), 1 << 20)
    np.testing.assert_array_equal(back["actions"], got["a"])


def test_the_key_map_takes_libero_aloha_and_lerobot_names_and_says_what_is_missing(tmp_path):
    features = [FeatureSpec("observation.state", "float32", (2,)), FeatureSpec("observation.images.front", "uint8", (4, 4, 3))]
    km = KeyMap(features)
    img = np.zeros((4, 4, 3), np.uint8)
    for obs in (
        {"observation/image": img, "observation/state": np.zeros(2), "prompt": "go"},
        {"images": {"front": np.zeros((3, 4, 4), np.uint8)}, "state": np.zeros(2, np.float32), "prompt": "go"},  # ALOHA: CHW
        {"observation.images.front": img, "observation.state": np.zeros(2, np.float32), "prompt": "go"},
    ):
        arrays, task = km.apply(obs)
        assert arrays["observation.images.front"].shape == (4, 4, 3) and arrays["observation.state"].dtype == np.float32
        assert task == "go"
    with pytest.raises(WireError, match="observation.state") as missing:
        km.apply({"observation/image": img})
    assert "keymap" in str(missing.value)
    with pytest.raises(WireError, match="NaN"):
        km.apply({"observation/image": img, "state": np.array([np.nan, 0.0])})
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps({"cam/top": "observation.images.front", "joints": "observation.state", "instruction": "task"}))
    arrays, task = KeyMap.load(features, str(mapping)).apply({"cam/top": img, "joints": np.ones(2), "instruction": "pick"})
    assert task == "pick" and arrays["observation.state"].tolist() == [1.0, 1.0]


def test_a_slow_client_or_a_hung_one_does_not_hold_the_others(server, tmp_path):
    """A client that connects and never sends holds a session slot, nothing else: another is served."""
    from websockets.sync.client import connect

    with connect(f"ws://127.0.0.1:{server.openpi.port}", compression=None, max_size=None) as idle:
        idle.recv()  # connected, then silent
        with connect(f"ws://127.0.0.1:{server.openpi.port}", compression=None, max_size=None) as ws:
            unpack(ws.recv(), 1 << 20)
            ws.send(pack({"observation/image": np.zeros((32, 32, 3), np.uint8), "observation/state": np.zeros(2), "prompt": "x"}))
            t = time.monotonic()
            reply = unpack(ws.recv(timeout=10), 1 << 20)
            assert reply["actions"].shape == (10, 2) and time.monotonic() - t < 5


@pytest.mark.subprocess
@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")
def test_with_tls_and_tokens_the_endpoint_is_wss_and_checks_the_api_key(tmp_path, monkeypatch):
    """The gRPC port's certificate serves wss://; openpi's ``api_key`` (``Authorization: Api-Key``)
    is checked against the server's tokens; a wrong key is told why and closed."""
    import ssl

    from websockets.sync.client import connect

    from lerobot_armory.entrypoints.openpi import endpoint

    # A loaded 2-core CI machine once took longer than the server's 10 s to finish a handshake
    # (the client was told nothing: "did not receive a valid HTTP response"); the server's
    # patience here matches the client's below. It takes milliseconds when the machine is idle.
    monkeypatch.setattr(endpoint, "OPEN_TIMEOUT_S", 60.0)

    key, cert = tmp_path / "key.pem", tmp_path / "cert.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out", str(cert), "-days", "1",
         "-subj", "/CN=localhost", "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"],
        check=True, capture_output=True,
    )  # fmt: skip
    tokens = tmp_path / "tokens.txt"
    tokens.write_text("fleet-token-0123456789abcdef\n")
    planner = make_planner(tmp_path / "planner")
    cfg = ServerConfig(
        policy=PolicyOptions(planner, "cpu"), engine=EngineOptions(emulate_profile="h100-pi05"), status_interval_s=0.0,
        log_level="warning", port=0, openpi=OpenpiOptions(port=0), tls_cert=str(cert), tls_key=str(key),
        auth_token_file=str(tokens),
    )  # fmt: skip
    server, summary = build_server(cfg)
    try:
        assert "wss://" in summary
        trust = ssl.create_default_context(cafile=str(cert))
        # 127.0.0.1 (in the certificate's names), not "localhost": the endpoint binds IPv4 only,
        # and a name that resolves to ::1 first can reach another process's port. The generous
        # open timeout is for a loaded 2-core CI machine (the handshake takes ms when idle).
        url = f"wss://127.0.0.1:{server.openpi.port}"
        with connect(url, ssl=trust, additional_headers={"Authorization": "Api-Key wrong"}, open_timeout=60) as ws:
            assert "api key" in ws.recv()
        good = {"Authorization": "Api-Key fleet-token-0123456789abcdef"}
        with connect(url, ssl=trust, additional_headers=good, compression=None, max_size=None, open_timeout=60) as ws:
            unpack(ws.recv(), 1 << 20)
            ws.send(pack({"observation/image": np.zeros((32, 32, 3), np.uint8), "observation/state": np.zeros(2)}))
            assert unpack(ws.recv(timeout=10), 1 << 20)["actions"].shape == (10, 2)
        with pytest.raises(Exception):  # noqa: B017 - plaintext against a TLS port fails in the handshake
            with connect(f"ws://127.0.0.1:{server.openpi.port}", open_timeout=3) as ws:
                ws.recv(timeout=3)
    finally:
        server.stop()


def test_a_chunk_left_over_from_a_timed_out_request_never_answers_the_next_one(server):
    from websockets.sync.client import connect

    from lerobot_armory.serving.messages import ChunkOut

    obs = {"observation/image": np.zeros((32, 32, 3), np.uint8), "observation/state": np.zeros(2)}
    with connect(f"ws://127.0.0.1:{server.openpi.port}", compression=None, max_size=None) as ws:
        unpack(ws.recv(), 1 << 20)
        ws.send(pack(obs))  # the first request registers the connection as a robot
        unpack(ws.recv(timeout=10), 1 << 20)
        with server.fleet.cond:
            mine = [s for s in server.fleet.sessions.values() if s.robot_id.startswith("openpi-")][-1]
        stale = np.full((10, 2), 99.0, np.float32)
        mine.outbox.put(ChunkOut(999, 0, stale, 0.0, 0.0))
        ws.send(pack(obs))
        reply = unpack(ws.recv(timeout=10), 1 << 20)
        assert not np.any(reply["actions"] == 99.0)
