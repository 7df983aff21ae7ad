"""Swapping the served checkpoint live (serving/swap.py, entrypoints/grpc/admin.py, lerobot-armory-admin).

Two tiny ACTs with the same features and different random weights; robots stream while the
operator swaps; every chunk is checked against the checkpoint that must have computed it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import grpc
import numpy as np
import pytest
from prometheus_client import generate_latest

from lerobot_armory.engine.options import PolicyOptions
from lerobot_armory.engine.policy_engine import PolicyEngine
from lerobot_armory.entrypoints.grpc.service import PolicyInfo
from lerobot_armory.entrypoints.server import ArmoryServer, policy_loader
from lerobot_armory.entrypoints.status import render
from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import ArmoryAdminStub
from lerobot_armory.proto.limits import TOKEN_KEY
from lerobot_armory.schedulers import EarliestDeadlineConfig
from lerobot_armory.serving.security import AuthTokens, OperatorTokens
from tests.conftest import TINY
from tests.support.pusher import Pusher, observation, wait_for

OPERATOR = "operator-token-0123456789abcdef"
ROBOT = "robot-fleet-token-0123456789abcd"


def _make(tmp_path_factory, name: str, **changes) -> Path:
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

    out = tmp_path_factory.mktemp(name) / name
    make_demo_policy(DemoPolicyConfig(output=str(out), **{**TINY, **changes}))
    return out


@pytest.fixture(scope="module")
def new_dir(tmp_path_factory):
    return _make(tmp_path_factory, "act-seed1", seed=1)


@pytest.fixture(scope="module")
def new_engine(new_dir):
    return PolicyEngine(PolicyOptions(str(new_dir), "cpu"))


def start(engine, operators: OperatorTokens | None = OperatorTokens([OPERATOR]), auth: AuthTokens | None = None) -> ArmoryServer:
    profile = LatencyProfile("test", (20.0, 24.0, 28.0))
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    return ArmoryServer(
        engine, info, profile, EarliestDeadlineConfig(), 3, port=0, auth=auth, operators=operators,
        loader=policy_loader(profile_reps=1),
    ).start()  # fmt: skip


def admin(server: ArmoryServer, token: str | None = OPERATOR) -> ArmoryAdminStub:
    channel = grpc.insecure_channel(server.address)
    stub = ArmoryAdminStub(channel)
    md = ((TOKEN_KEY, token),) if token is not None else ()

    class Calls:
        def swap(self, path, drain=False, overrides=()):
            return stub.SwapPolicy(pb.SwapRequest(policy_path=str(path), drain=drain, overrides=list(overrides)), metadata=md, timeout=120)

        def status(self):
            return stub.Status(pb.AdminStatusRequest(), metadata=md, timeout=10)

    return Calls()


def _expected(engine, robot: int, i_start: int) -> np.ndarray:
    return engine.infer([observation(robot, i_start)], [""])[0]


def check_chunks(server: ArmoryServer, robots: list[Pusher], switches: list[tuple[int, object]], first) -> list[int]:
    """Every chunk a robot received came from the checkpoint serving when its batch ran:
    ``first`` before the first switch, then each ``(batch count at the switch, engine)``.
    Returns how many were checked on each engine (``first``, then each switch's)."""
    by_id = {f"pusher{r.k}": r for r in robots}
    checked = [0] * (1 + len(switches))
    for n, record in enumerate(server.batch_log):
        if not record.ok:
            continue
        engine, which = first, 0
        for j, (at, eng) in enumerate(switches):
            if n >= at:
                engine, which = eng, j + 1
        for robot_id, chunk_id, i_start in zip(record.robots, record.chunk_ids, record.i_starts, strict=True):
            robot = by_id[robot_id]
            chunk = next((c for c in robot.chunks if c.chunk_id == chunk_id), None)
            if chunk is None:
                continue  # on its way when the robot stopped
            np.testing.assert_allclose(chunk.actions, _expected(engine, robot.k, i_start), atol=1e-4)
            checked[which] += 1
    return checked


def no_trouble(robots: list[Pusher]) -> None:
    for r in robots:
        assert r.closed_with is None, r.closed_with
        bad = [n for n in r.notices if n.kind in (pb.Notice.INFERENCE_FAILED, pb.Notice.DROPPED, pb.Notice.SHUTDOWN)]
        assert not bad, bad


@pytest.mark.slow
@pytest.mark.parametrize("drain", [False, True])
def test_live_swap_under_a_streaming_fleet(engine, new_engine, demo_policy_dir, new_dir, drain):
    old_probe = _expected(engine, 0, 0)
    assert not np.allclose(old_probe, _expected(new_engine, 0, 0), atol=1e-3), "the two checkpoints must differ"
    server = start(engine)
    robots = [Pusher(server.address, engine, k).start() for k in range(3)]
    try:
        assert wait_for(lambda: all(len(r.chunks) >= 5 for r in robots), timeout=30)
        reply = admin(server).swap(new_dir, drain=drain)
        assert reply.result == "ok", reply.message
        assert reply.old_path == str(demo_policy_dir) and reply.new_path == str(new_dir)
        at = server.loop.switched_at_batch
        counts = [len(r.chunks) for r in robots]
        assert wait_for(lambda: all(len(r.chunks) >= c + 5 for r, c in zip(robots, counts, strict=True)), timeout=30)
        status = admin(server).status()
        assert status.policy_path == str(new_dir) and status.swaps_ok == 1 and status.robots == 3
        assert "swaps=ok:1" in server.status_line()
    finally:
        for r in robots:
            r.stop()
        server.stop(grace_s=0.5)
    no_trouble(robots)
    assert at is not None and 0 < at < len(server.batch_log)
    before, after = check_chunks(server, robots, [(at, new_engine)], engine)
    assert before >= 15 and after >= 15, (before, after)
    # and the chunks arrived in that order: no old chunk reached a robot after a new one
    for r in robots:
        new = [np.allclose(c.actions, _expected(new_engine, r.k, c.i_start), atol=1e-4) for c in r.chunks]
        assert new == sorted(new) and new[-1], new
    text = server.metrics.registry.get_sample_value("armory_policy_swaps_total", {"result": "ok"})
    assert text == 1.0
    assert server.metrics.registry.get_sample_value("armory_policy_info", {"policy": "default", "path": str(new_dir)}) == 1.0
    view = render(generate_latest(server.metrics.registry).decode())
    assert f"policy {new_dir}; swaps ok 1, refused 0, failed 0, last took" in view


def test_admin_calls_without_the_operator_token_are_refused(engine, new_dir):
    server = start(engine, auth=AuthTokens(fleet=[ROBOT]))
    off = start(engine, operators=None)
    try:
        for token, code in ((None, grpc.StatusCode.UNAUTHENTICATED), ("", grpc.StatusCode.UNAUTHENTICATED),
                            (ROBOT, grpc.StatusCode.UNAUTHENTICATED), (OPERATOR + "x", grpc.StatusCode.UNAUTHENTICATED)):  # fmt: skip
            for call in (lambda c: c.swap(new_dir), lambda c: c.status()):
                with pytest.raises(grpc.RpcError) as err:
                    call(admin(server, token))
                assert err.value.code() == code
        with pytest.raises(grpc.RpcError) as err:
            admin(off).swap(new_dir)
        assert err.value.code() == grpc.StatusCode.PERMISSION_DENIED
        assert "--operator_token_file" in err.value.details()
        for s in (server, off):
            assert s.swapper.current.path == engine.path and s.loop.engine is engine
            assert not any(s.swapper.counts.by_result.values())
    finally:
        server.stop(grace_s=0.5)
        off.stop(grace_s=0.5)


def test_operator_tokens_file_refuses_a_robot_token(tmp_path):
    (tmp_path / "robots").write_text(ROBOT + "\n")
    (tmp_path / "ops").write_text(f"# operators\n{ROBOT}\n")
    with pytest.raises(ConfigError, match="must differ from robot tokens"):
        OperatorTokens.load(str(tmp_path / "ops"), AuthTokens.load(str(tmp_path / "robots")))
    (tmp_path / "ops").write_text(OPERATOR + "\n")
    ops = OperatorTokens.load(str(tmp_path / "ops"), AuthTokens.load(str(tmp_path / "robots")))
    assert ops.check(OPERATOR) and not ops.check(ROBOT) and not ops.check("")


@pytest.mark.slow
def test_bad_swaps_are_refused_and_the_old_policy_keeps_serving(engine, tmp_path, tmp_path_factory):
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "model.safetensors").write_bytes(b"garbage" * 100)
    garbage = tmp_path / "garbage"
    garbage.mkdir()
    (garbage / "config.json").write_text((Path(engine.path) / "config.json").read_text())
    (garbage / "model.safetensors").write_bytes(b"\x00" * 64)
    state3 = _make(tmp_path_factory, "act-state3", state_dim=3, seed=2)
    chunk12 = _make(tmp_path_factory, "act-chunk12", chunk_size=12, seed=3)
    server = start(engine)
    robot = Pusher(server.address, engine, 0).start()
    try:
        assert wait_for(lambda: len(robot.chunks) >= 3, timeout=30)
        calls = admin(server)
        for path, result, words in (
            (broken, "failed", "cannot load"),
            (garbage, "failed", "cannot load"),
            (tmp_path / "missing", "failed", "cannot load"),
            (state3, "refused", "feature observation.state: float32[2] -> float32[3]"),
            (chunk12, "refused", "chunk size 10 -> 12"),
        ):
            reply = calls.swap(path)
            assert reply.result == result and words in reply.message, reply.message
            assert "keeps serving" in reply.message
            assert server.swapper.current.path == engine.path and server.loop.engine is engine
        reply = calls.swap(broken, drain=True)  # drained, failed, the old checkpoint loaded again
        assert reply.result == "failed" and "serves again" in reply.message, reply.message
        n = len(robot.chunks)
        assert wait_for(lambda: len(robot.chunks) >= n + 5, timeout=30)
        assert server.swapper.counts.by_result == {"ok": 0, "refused": 2, "failed": 4}
        assert server.metrics.registry.get_sample_value("armory_policy_swaps_total", {"result": "failed"}) == 4.0
    finally:
        robot.stop()
        server.stop(grace_s=0.5)
    no_trouble([robot])
    # every chunk, before and after the reload, is the (same) old checkpoint's
    assert check_chunks(server, [robot], [], engine)[0] > 5


@pytest.mark.slow
@pytest.mark.subprocess
def test_admin_cli_swaps_and_refuses_with_exit_codes(engine, new_dir, tmp_path):
    token_file = tmp_path / "operator.txt"
    token_file.write_text(OPERATOR + "\n")
    wrong = tmp_path / "wrong.txt"
    wrong.write_text("not-the-operator-token-at-all\n")
    server = start(engine)
    exe = str(Path(sys.executable).with_name("lerobot-armory-admin"))
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}

    def run(*args):
        return subprocess.run([exe, *args], capture_output=True, text=True, timeout=180, env=env)

    try:
        ok = run("swap", f"--address={server.address}", f"--operator_token_file={token_file}", f"--policy.path={new_dir}")
        assert ok.returncode == 0, ok.stderr
        lines = ok.stdout.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"swapped {engine.path} -> {new_dir}"), ok.stdout
        status = run("status", f"--address={server.address}", f"--operator_token_file={token_file}")
        assert status.returncode == 0 and f"policy {new_dir}" in status.stdout
        denied = run("swap", f"--address={server.address}", f"--operator_token_file={wrong}", f"--policy.path={engine.path}")
        assert denied.returncode == 3 and "UNAUTHENTICATED" in denied.stderr and not denied.stdout
        refused = run("swap", f"--address={server.address}", f"--operator_token_file={token_file}", f"--policy.path={tmp_path}")
        assert refused.returncode == 1 and refused.stderr.startswith("swap failed:"), refused.stderr
        usage = run("swap", f"--address={server.address}")
        assert usage.returncode == 2 and "policy.path" in usage.stderr
    finally:
        server.stop(grace_s=0.5)
    assert server.swapper.current.path == str(new_dir)


def test_openpi_clients_connecting_after_a_swap_are_told_the_new_policy(engine, new_dir):
    from websockets.sync.client import connect

    from lerobot_armory.entrypoints.openpi.codec import unpack
    from lerobot_armory.serving.config import OpenpiOptions

    server = start(engine)
    try:
        port = server.serve_openpi(OpenpiOptions(port=0))

        def handshake() -> dict:
            with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
                return unpack(ws.recv(), 1 << 20)

        assert str(new_dir) not in handshake()["policy"]
        assert admin(server).swap(new_dir).result == "ok"
        assert str(new_dir) in handshake()["policy"]
    finally:
        server.stop(grace_s=0.5)


def test_two_policies_on_one_path_each_keep_their_info_sample_through_a_swap():
    import time

    from lerobot_armory.serving.fleet import Fleet
    from lerobot_armory.serving.loop import LoopStats
    from lerobot_armory.serving.metrics import ServerMetrics
    from lerobot_armory.serving.swap import SwapResult

    metrics = ServerMetrics(Fleet(time.monotonic), LoopStats(), max_batch_size=2)
    metrics.set_policy("kitchen", "/ckpt/base")
    metrics.set_policy("sorting", "/ckpt/base")
    metrics.on_swap(SwapResult("ok", "swapped", "/ckpt/base", "/ckpt/sorting-v2", 1.0), policy="sorting")
    info = metrics.registry.get_sample_value
    assert info("armory_policy_info", {"policy": "kitchen", "path": "/ckpt/base"}) == 1.0  # the other keeps its sample
    assert info("armory_policy_info", {"policy": "sorting", "path": "/ckpt/sorting-v2"}) == 1.0
    assert info("armory_policy_info", {"policy": "sorting", "path": "/ckpt/base"}) is None
