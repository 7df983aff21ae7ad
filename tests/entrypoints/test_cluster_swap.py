"""A rolling checkpoint swap through a cluster front (``lerobot-armory-admin swap --address=FRONT``).

Two in-process replicas (:class:`LocalReplicas`) serve the tiny ACT; robots stream on both while
the front swaps one replica at a time. Every chunk is checked against the checkpoint that must
have computed it (the new one computed alone by a :class:`PolicyEngine`).
"""

from __future__ import annotations

import grpc
import numpy as np
import pytest

from lerobot_armory.engine.options import EngineOptions, PolicyOptions
from lerobot_armory.entrypoints.cluster.front import ClusterFront, FrontOptions, FrontServer
from lerobot_armory.entrypoints.cluster.replica import ArmoryReplica, LocalReplicas
from lerobot_armory.entrypoints.server import ServerConfig
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import ArmoryAdminStub
from lerobot_armory.proto.limits import TOKEN_KEY
from lerobot_armory.schedulers import EarliestDeadlineConfig
from lerobot_armory.serving.security import OperatorTokens
from tests.serving.test_swap import OPERATOR, _expected, check_chunks, new_dir, new_engine, no_trouble  # noqa: F401 - fixtures
from tests.support.pusher import Pusher, wait_for


def replica_cfg(policy_dir, token_file) -> ServerConfig:
    # An emulated profile: both replicas report the same d_infer. Profiled on a busy machine, one
    # replica measured slower, placement by predicted load put all four robots on the other, and
    # without rebalancing they stayed there (these tests need robots on both replicas).
    return ServerConfig(
        policy=PolicyOptions(str(policy_dir), "cpu"), scheduler=EarliestDeadlineConfig(), max_batch_size=3,
        status_interval_s=0.0, log_level="warning", port=0, operator_token_file=str(token_file),
        engine=EngineOptions(emulate_profile="h100-pi05"),
    )  # fmt: skip


@pytest.fixture(scope="module")
def token_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("ops") / "operator.txt"
    path.write_text(OPERATOR + "\n")
    return path


@pytest.fixture
def cluster(demo_policy_dir, token_file):
    """2 in-process replicas of the tiny ACT and a front with the operator token; stopped afterwards."""
    cfg = replica_cfg(demo_policy_dir, token_file)
    replicas = LocalReplicas({f"r{k}": ArmoryReplica(cfg, f"r{k}") for k in range(2)})
    front = FrontServer(ClusterFront(replicas, FrontOptions(health_interval_s=0.2, rebalance=False)), operators=OperatorTokens([OPERATOR]))
    yield front, replicas, cfg
    front.stop(0)
    for rid in replicas.ids():
        replicas.kill(rid)


def admin(address: str, token: str | None = OPERATOR):
    stub = ArmoryAdminStub(grpc.insecure_channel(address))
    md = ((TOKEN_KEY, token),) if token is not None else ()
    swap = lambda path: stub.SwapPolicy(pb.SwapRequest(policy_path=str(path)), metadata=md, timeout=120)  # noqa: E731
    status = lambda: stub.Status(pb.AdminStatusRequest(), metadata=md, timeout=10)  # noqa: E731
    return swap, status


@pytest.mark.slow
def test_a_rolling_swap_switches_one_replica_at_a_time_under_streaming_robots(cluster, engine, new_engine, new_dir, demo_policy_dir):
    front, replicas, cfg = cluster
    assert not np.allclose(_expected(engine, 0, 0), _expected(new_engine, 0, 0), atol=1e-3)
    robots = [Pusher(front.address, engine, k).start() for k in range(4)]
    try:
        assert wait_for(lambda: len(front.front.placements()) == 4 and len(set(front.front.placements().values())) == 2, timeout=20)
        assert wait_for(lambda: all(len(r.chunks) >= 5 for r in robots), timeout=30)
        where = front.front.placements()
        swap, status = admin(front.address)
        reply = swap(new_dir)
        assert reply.result == "ok", reply.message
        assert reply.message == f"r0,r1 serve {new_dir}" and reply.old_path == str(demo_policy_dir), reply
        counts = [len(r.chunks) for r in robots]
        assert wait_for(lambda: all(len(r.chunks) >= c + 5 for r, c in zip(robots, counts, strict=True)), timeout=30)
        assert front.front.placements() == where  # nobody moved
        seen = lambda: [(r.replica_id, r.up, r.policy_path, r.swaps_ok, r.robots) for r in status().replicas]  # noqa: E731
        want = [(rid, True, str(new_dir), 1, list(where.values()).count(rid)) for rid in ("r0", "r1")]
        assert wait_for(lambda: seen() == want, timeout=5), seen()  # as of the front's next health check
        s = status()
        assert s.policy_path == str(new_dir) and s.swaps_ok == 1 and s.robots == 4
    finally:
        for r in robots:
            r.stop()
    no_trouble(robots)

    for rid in replicas.ids():
        server = replicas.replicas[rid].server
        mine = [r for r in robots if where[f"pusher{r.k}"] == rid]
        at = server.loop.switched_at_batch
        assert at is not None and 0 < at < len(server.batch_log)
        before, after = check_chunks(server, robots, [(at, new_engine)], engine)
        assert before >= 5 and after >= 5, (rid, before, after)

        for r in mine:  # old chunks, then new ones: never an old chunk after a new one
            new = [np.allclose(c.actions, _expected(new_engine, r.k, c.i_start), atol=1e-4) for c in r.chunks]
            assert new == sorted(new) and new[-1], new
    # a replica that restarts (as Ray would: with the options the cluster started with) is brought
    # to the cluster's policy before robots are placed on it
    replicas.kill("r0")
    replicas.replicas["r0"] = ArmoryReplica(cfg, "r0")
    assert replicas.replicas["r0"].server.swapper.current.path == str(demo_policy_dir)
    assert wait_for(lambda: replicas.replicas["r0"].server.swapper.current.path == str(new_dir), timeout=30)
    assert wait_for(lambda: front.front.state["r0"].view.healthy, timeout=5)


def test_a_roll_that_fails_on_the_first_replica_leaves_every_replica_on_the_old_path(cluster, engine, demo_policy_dir, tmp_path, new_dir):
    front, replicas, _ = cluster
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "model.safetensors").write_bytes(b"garbage" * 100)
    robot = Pusher(front.address, engine, 0).start()
    try:
        assert wait_for(lambda: len(robot.chunks) >= 3, timeout=30)
        swap, status = admin(front.address)
        reply = swap(broken)
        assert reply.result == "failed", reply.message
        assert reply.message.startswith("stopped at r0 (failed: cannot load") and reply.message.endswith(f"r0,r1 serve {demo_policy_dir}"), reply.message
        assert len(reply.message.splitlines()) == 1
        for rid in replicas.ids():
            assert replicas.replicas[rid].server.swapper.current.path == str(demo_policy_dir)
        assert replicas.replicas["r1"].server.swapper.counts.by_result == {"ok": 0, "refused": 0, "failed": 0}  # never asked
        s = status()
        assert s.policy_path == str(demo_policy_dir) and s.swaps_failed == 1 and s.swaps_ok == 0
        assert [r.policy_path for r in s.replicas] == [str(demo_policy_dir)] * 2
        n = len(robot.chunks)
        assert wait_for(lambda: len(robot.chunks) >= n + 5, timeout=30)
    finally:
        robot.stop()
    no_trouble([robot])
    # without the operator token the front refuses, and nothing changes
    for token in (None, "", OPERATOR + "x"):
        swap, status = admin(front.address, token)
        for call in (lambda: swap(new_dir), status):
            with pytest.raises(grpc.RpcError) as err:
                call()
            assert err.value.code() == grpc.StatusCode.UNAUTHENTICATED
    off = FrontServer(ClusterFront(replicas, FrontOptions(health_interval_s=0.2)))  # no --operator_token_file
    try:
        with pytest.raises(grpc.RpcError) as err:
            admin(off.address)[0](new_dir)
        assert err.value.code() == grpc.StatusCode.PERMISSION_DENIED
    finally:
        off.stop(0)
    assert all(replicas.replicas[rid].server.swapper.current.path == str(demo_policy_dir) for rid in replicas.ids())
    assert front.front.rolls == {"ok": 0, "refused": 0, "failed": 1}
