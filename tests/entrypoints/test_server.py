"""A real server on an ephemeral loopback port, the tiny ACT, and several concurrent robots."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import grpc
import numpy as np
import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto import armory_pb2_grpc
from lerobot_armory.proto.armory_pb2_grpc import ArmoryServicer, ArmoryStub
from lerobot_armory.entrypoints.grpc.hardening import add_armory_to_server, rpc_names
from lerobot_armory.proto.limits import SERVICE_NAME
from lerobot_armory.robot.client import ArmoryClient, RegistrationRefused, RobotIdentity
from lerobot_armory.robot.connection import Connection
from lerobot_armory.schedulers import EarliestDeadlineConfig, LookaheadConfig
from lerobot_armory.entrypoints.server import ArmoryServer
from lerobot_armory.entrypoints.grpc.service import PolicyInfo
from tests.support.pusher import IMAGE, STATE, Pusher, features, observation, wait_for


@pytest.fixture
def server(engine):
    profile = LatencyProfile("test", (20.0, 24.0, 28.0, 32.0))
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    srv = ArmoryServer(engine, info, profile, EarliestDeadlineConfig(), 3, port=0, max_message_bytes=256 << 10).start()
    yield srv
    srv.stop(grace_s=0.5)


ROOT = Path(__file__).resolve().parents[2]
PROTO = "lerobot_armory/proto/armory.proto"
GENERATED = ("armory_pb2.py", "armory_pb2.pyi", "armory_pb2_grpc.py")


def version(text: str) -> tuple[int, ...]:
    return tuple(int(part) for part in text.split("."))


@pytest.mark.subprocess
def test_generated_code_is_up_to_date_with_the_proto(tmp_path):
    """The committed armory_pb2*.py(i) are byte for byte what `make proto` makes from armory.proto."""
    pytest.importorskip("grpc_tools.protoc", reason="grpcio-tools (the dev extra) is not installed")
    from importlib.metadata import version as installed

    tools = installed("grpcio-tools")
    if tools != armory_pb2_grpc.GRPC_GENERATED_VERSION:  # another generator writes other version stamps
        pytest.skip(f"grpcio-tools {tools} installed; the committed code was made by {armory_pb2_grpc.GRPC_GENERATED_VERSION}")
    # the command of the Makefile's `proto` target, writing into tmp_path
    out = [f"--{kind}_out={tmp_path}" for kind in ("python", "pyi", "grpc_python")]
    subprocess.run([sys.executable, "-m", "grpc_tools.protoc", "-I.", *out, PROTO], cwd=ROOT, check=True)
    for name in GENERATED:
        fresh = (tmp_path / "lerobot_armory/proto" / name).read_bytes()
        assert fresh == (ROOT / "lerobot_armory/proto" / name).read_bytes(), f"{name} is stale: run `make proto`"


def test_generated_grpc_code_needs_no_grpcio_above_our_floor():
    """armory_pb2_grpc refuses to import under a grpcio older than the grpcio-tools that made it."""
    dependencies = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    floor = next(d.removeprefix("grpcio>=") for d in dependencies if d.startswith("grpcio>="))
    assert version(armory_pb2_grpc.GRPC_GENERATED_VERSION) <= version(floor)
    assert version(grpc.__version__) >= version(armory_pb2_grpc.GRPC_GENERATED_VERSION)  # it imported, so this holds


def test_server_binding_serves_the_proto_service():
    """The server binds every RPC armory.proto declares, under the service name the protocol constants give."""
    service = pb.DESCRIPTOR.services_by_name["Armory"]
    assert service.full_name == SERVICE_NAME
    assert sorted(rpc_names()) == sorted(m.name for m in service.methods)


@pytest.mark.parametrize("subclass", [False, True])
def test_binding_a_servicer_without_every_rpc_fails_at_once(subclass):
    class OnlyRegister(ArmoryServicer if subclass else object):  # the base's Stream would answer UNIMPLEMENTED
        def Register(self, request, context):  # noqa: N802 - the RPC's name
            return pb.RegisterResponse()

    server = grpc.server(None)
    with pytest.raises(TypeError, match="'Stream'"):
        add_armory_to_server(OnlyRegister(), server)


def test_batches_form_and_each_robot_gets_its_own_chunk(server, engine):
    # Every robot registered before any pushes: their first requests then wait together (each
    # registration is a round trip; started one by one, the robots' phases could stay staggered and
    # the deadline scheduler rightly serve each alone — seen once in a full run: 20 batches of 1).
    robots = [Pusher(server.address, engine, k) for k in range(4)]
    for r in robots:
        r.start()
    assert wait_for(lambda: all(len(r.chunks) >= 4 for r in robots), timeout=20)
    for r in robots:
        r.stop()
    server.stop(grace_s=0.5)
    sizes = server.loop.stats.batch_sizes
    assert max(sizes) > 1, f"no batch larger than 1 formed: {sizes}"
    assert max(sizes) <= 3
    # Every chunk is the deterministic ACT's answer to *that robot's* observation i_start.
    for r in robots:
        assert all(c.actions.shape == (engine.chunk_size, engine.action_dim) for c in r.chunks)
        starts = [c.i_start for c in r.chunks]
        assert starts == sorted(starts) and len(set(starts)) == len(starts)
        for c in r.chunks[:4]:
            solo = engine.infer([observation(r.k, c.i_start)], ["x"])[0]
            np.testing.assert_allclose(c.actions, solo, rtol=1e-4, atol=1e-4)
            other = engine.infer([observation((r.k + 1) % 4, c.i_start)], ["x"])[0]
            assert not np.allclose(c.actions, other, atol=1e-4), "chunk does not depend on the robot's own observation"


@pytest.mark.slow
def test_mirror_prediction_follows_a_real_control_loop(server, engine):
    rng = np.random.default_rng(0)
    executed = []
    client = ArmoryClient(
        server.address,
        RobotIdentity("loop", fps=20, h_min=2, h_max=8, tier="fast"),
        features(engine),
        observe=lambda: {STATE: rng.standard_normal(2).astype(np.float32), IMAGE: np.zeros((32, 32, 3), np.uint8)},
        act=executed.append,
    )
    stats = client.run(duration_s=3.0)
    with server.fleet.cond:
        session = next(s for s in server.fleet.sessions.values() if s.robot_id == "loop")
        error, reported = session.counters.index_error, session.counters.reported_index
    client.close()
    assert stats["executed_steps"] == len(executed) > 20
    assert stats["executed_steps"] + stats["starved_steps"] == stats["ticks"]
    assert reported is not None and error is not None
    assert error <= 2, f"mirror predicted index is {error} steps away from the robot's report"
    assert sum(stats["first_executed_index"].values()) >= 1


def bad_observations(engine):
    ok = observation(9, 0)
    raw = pb.Tensor(name=STATE, dtype="float32", shape=[2], data=b"\x00" * 5)
    nan = dict(ok)
    nan[STATE] = np.array([np.nan, 0.0], np.float32)
    return {
        "wrong dtype": {**ok, STATE: ok[STATE].astype(np.float64)},
        "wrong shape": {**ok, STATE: np.zeros(3, np.float32)},
        "missing feature": {STATE: ok[STATE]},
        "extra feature": {**ok, "observation.extra": np.zeros(1, np.float32)},
        "nan": nan,
        "byte length": raw,
    }


def test_each_bad_observation_is_rejected_while_others_are_served(server, engine):
    good = Pusher(server.address, engine, 0).start()
    conn = Connection(server.address)
    conn.register("bad", features(engine), fps=20, h_min=1, h_max=5)
    notices = []
    conn.open_stream(lambda c: None, notices.append)
    expected = {
        "wrong dtype": "registered float32",
        "wrong shape": "registered float32[2]",
        "missing feature": "missing feature",
        "extra feature": "unexpected feature",
        "nan": "NaN",
        "byte length": "bytes",
    }
    for k, (name, obs) in enumerate(bad_observations(engine).items()):
        if isinstance(obs, pb.Tensor):
            img = observation(9, 0)[IMAGE]
            from lerobot_armory.wire import encode

            conn.send_raw(pb.RobotMessage(observation=pb.Observation(index=k, capture_time=time.monotonic(), tensors=[obs, encode(IMAGE, img)])))
        else:
            conn.send_observation(k, obs)
    # an index going backwards after a good observation
    conn.send_observation(10, observation(9, 10))
    conn.send_observation(4, observation(9, 4))
    assert wait_for(lambda: len(notices) >= 7)
    texts = [n.message for n in notices if n.kind == pb.Notice.REJECTED_OBSERVATION]
    for name, fragment in expected.items():
        assert any(fragment in t for t in texts), f"{name}: no rejection mentioning {fragment!r} in {texts}"
    assert any("backwards" in t for t in texts)
    before = len(good.chunks)
    assert wait_for(lambda: len(good.chunks) >= before + 3), "the well-behaved robot stopped receiving chunks"
    conn.close()
    good.stop()


def test_registration_mismatches_are_all_listed(server, engine):
    conn = Connection(server.address)
    with pytest.raises(grpc.RpcError) as info:
        conn.register("mis", {STATE: ("float32", (3,)), "observation.other": ("float32", (1,))}, fps=0, h_min=60, h_max=50)
    assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    details = info.value.details()
    for fragment in ("fps", "h_max", "h_min", "observation.state", "missing feature 'observation.images.front'", "unexpected feature 'observation.other'"):
        assert fragment in details, f"{fragment!r} not in {details!r}"
    conn.close()


def test_duplicate_robot_id_and_stream_without_registration(server, engine):
    first = Pusher(server.address, engine, 0, robot_id="twin").start()
    conn = Connection(server.address)
    with pytest.raises(grpc.RpcError) as info:
        conn.register("twin", features(engine), fps=20, h_min=1, h_max=5)
    assert info.value.code() == grpc.StatusCode.ALREADY_EXISTS
    # A stream with no (or a made-up) session is refused before any observation is read.
    stub = ArmoryStub(conn.channel)
    call = stub.Stream(iter([pb.RobotMessage(observation=pb.Observation(index=0))]), metadata=(("armory-session", "made-up"),))
    with pytest.raises(grpc.RpcError) as info:
        list(call)
    assert info.value.code() == grpc.StatusCode.FAILED_PRECONDITION
    conn.close()
    before = len(first.chunks)
    assert wait_for(lambda: len(first.chunks) > before)
    first.stop()


def test_oversized_message_and_dropped_stream_hurt_nobody_else(server, engine):
    good = Pusher(server.address, engine, 0).start()
    big = Connection(server.address)
    big.register("big", features(engine), fps=20, h_min=1, h_max=5)
    closed = threading.Event()
    errors = []
    big.open_stream(lambda c: None, None, lambda e: (errors.append(e), closed.set()))
    huge = pb.Tensor(name=STATE, dtype="float32", shape=[100_000], data=b"\x00" * 400_000)
    big.send_raw(pb.RobotMessage(observation=pb.Observation(index=0, tensors=[huge])))
    assert closed.wait(10)
    assert errors[0] is not None and errors[0].code() == grpc.StatusCode.RESOURCE_EXHAUSTED

    # A robot that vanishes while its request is in a batch.
    ghost = Connection(server.address)
    ghost.register("ghost", features(engine), fps=20, h_min=1, h_max=5)
    ghost.open_stream(lambda c: None)
    ghost.send_observation(0, observation(5, 0))
    time.sleep(0.01)
    ghost.close()
    assert wait_for(lambda: all(s.robot_id not in ("ghost", "big") for s in server.fleet.sessions.values()))
    before = len(good.chunks)
    assert wait_for(lambda: len(good.chunks) >= before + 3)
    good.stop()


def test_health_check_and_graceful_stop(server, engine):
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    channel = grpc.insecure_channel(server.address)
    health = health_pb2_grpc.HealthStub(channel)
    assert health.Check(health_pb2.HealthCheckRequest(service="")).status == health_pb2.HealthCheckResponse.SERVING
    robot = Pusher(server.address, engine, 0).start()
    assert wait_for(lambda: len(robot.chunks) >= 1)
    server.stop(grace_s=1.0)
    assert wait_for(lambda: robot.conn.closed.is_set(), timeout=10)
    assert any(n.kind == pb.Notice.SHUTDOWN for n in robot.notices)
    robot.stop()
    channel.close()


def test_registration_refused_surfaces_the_reason(server, engine):
    client = ArmoryClient(
        server.address, RobotIdentity("nope", fps=20, h_min=1, h_max=99), features(engine), observe=dict, act=lambda a: None
    )
    with pytest.raises(RegistrationRefused, match="h_max"):
        client.connect()


def test_engine_failure_hits_one_batch_only(server, engine, monkeypatch):
    robot = Pusher(server.address, engine, 0).start()
    assert wait_for(lambda: len(robot.chunks) >= 1)
    real = engine.infer
    calls = {"n": 0}

    def flaky(obs, tasks, noise_seeds=None, history=None):
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("simulated CUDA error")
        return real(obs, tasks, noise_seeds, history)

    monkeypatch.setattr(server.loop.engine, "infer", flaky)
    assert wait_for(lambda: any(n.kind == pb.Notice.INFERENCE_FAILED for n in robot.notices))
    before = len(robot.chunks)
    assert wait_for(lambda: len(robot.chunks) >= before + 2), "robot not served again after a failed batch"
    assert server.loop.stats.failed_batches == 1
    robot.stop()


def test_engine_rejects_missing_and_non_chunking_policies(engine, tmp_path, monkeypatch):
    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.engine.options import PolicyOptions

    with pytest.raises(ConfigError, match="policy.path"):
        PolicyEngine(PolicyOptions(str(tmp_path / "nothing-here"), "cpu"))
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "config.json").write_text("{not json")
    with pytest.raises(ConfigError, match="cannot load policy"):
        PolicyEngine(PolicyOptions(str(tmp_path / "broken"), "cpu"))

    def not_chunking(batch):
        raise NotImplementedError("returns single actions")

    monkeypatch.setattr(engine.policy, "predict_action_chunk", not_chunking)
    with pytest.raises(ConfigError, match="does not predict action chunks"):
        engine._dry_run()


def test_server_cli_fails_with_one_line_on_a_missing_policy(capsys, tmp_path):
    import logging

    from lerobot_armory.entrypoints.server import main

    # main() points the root logger at this test's captured stderr, which closes when the test
    # ends: left there, every later log line of any test's server thread fails to write.
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    try:
        with pytest.raises(SystemExit) as info:
            main([f"--policy.path={tmp_path / 'missing'}", "--port=0"])
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in err if "error" in line]
    assert len(errors) == 1 and "policy.path" in errors[0] and errors[0] == err[-1]
    assert not any("Traceback" in line for line in err)


def test_lookahead_serves_live_too(engine):
    profile = LatencyProfile("test", (20.0, 24.0, 28.0))
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    srv = ArmoryServer(engine, info, profile, LookaheadConfig(), 3, port=0).start()
    robots = [Pusher(srv.address, engine, k).start() for k in range(3)]
    try:
        assert wait_for(lambda: all(len(r.chunks) >= 3 for r in robots), timeout=20)
    finally:
        for r in robots:
            r.stop()
        srv.stop(grace_s=0.5)


@pytest.mark.slow
@pytest.mark.subprocess
def test_server_command_profiles_serves_and_exits_0_on_sigterm(demo_policy_dir, engine, tmp_path):
    """The real console entry point: start-up summary, saved profile, a robot served, SIGTERM -> exit 0."""
    import os
    import signal
    import subprocess
    import sys

    profile_path = tmp_path / "profile.json"
    proc = subprocess.Popen(
        [
            sys.executable, "-m", "lerobot_armory.entrypoints.server", f"--policy.path={demo_policy_dir}", "--policy.device=cpu",
            "--port=0", "--max_batch_size=2", f"--latency_profile={profile_path}", "--profile_reps=1", "--scheduler.type=edf",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip
    lines = []
    address = None
    deadline = time.monotonic() + 120
    while address is None and time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if "listening on" in line:
            address = line.split("listening on")[1].strip()
    assert address, "".join(lines)
    for _ in range(12):  # the rest of the summary
        lines.append(proc.stdout.readline())
    summary = "".join(lines)
    assert "chunk size H=10" in summary and "observation.images.front: uint8[32, 32, 3]" in summary
    assert "b=2" in summary and profile_path.is_file()
    robot = Pusher(address, engine, 0)
    robot.start()
    assert wait_for(lambda: len(robot.chunks) >= 2, timeout=30)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) == 0
    assert wait_for(lambda: robot.conn.closed.is_set(), timeout=10)
    assert any(n.kind == pb.Notice.SHUTDOWN for n in robot.notices)
    robot.stop()
    rest = proc.stdout.read()
    assert "stopped cleanly" in rest, rest


def test_an_engine_that_always_fails_stops_the_loop_instead_of_failing_forever(server, engine, monkeypatch):
    """An engine that fails every batch with an error not known as a lost device (those stop it at
    the first: tests/serving/test_device_faults.py): after MAX_CONSECUTIVE_FAILURES in a row the
    loop stops with an error (the server process then exits 1), robots are told each time."""
    from lerobot_armory.serving.loop import MAX_CONSECUTIVE_FAILURES

    def broken(obs, tasks, noise_seeds=None, history=None):
        raise RuntimeError("the model's weights were unloaded")

    monkeypatch.setattr(server.loop.engine, "infer", broken)
    robot = Pusher(server.address, engine, 0).start()
    try:
        assert wait_for(lambda: server.loop.error is not None, timeout=30)
        assert "failed batches in a row" in str(server.loop.error)
        assert server.loop.stats.failed_batches == MAX_CONSECUTIVE_FAILURES
        assert wait_for(lambda: not server.loop.alive, timeout=10)
        assert sum(n.kind == pb.Notice.INFERENCE_FAILED for n in robot.notices) >= 1
    finally:
        robot.stop()
