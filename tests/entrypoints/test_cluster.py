"""The cluster's front and replicas in one process (no Ray): placement, redirect, failover, moves, front restart.

The same front runs over Ray actors in test_cluster_ray.py; here the replicas are held in-process
(:class:`LocalReplicas`) so each behaviour is checked quickly and deterministically.
"""

from __future__ import annotations

import time
from collections import Counter

import grpc
import numpy as np
import pytest

from lerobot_armory.entrypoints.cluster.front import ClusterFront, FrontOptions, FrontServer
from lerobot_armory.entrypoints.cluster.replica import ArmoryReplica, LocalReplicas
from lerobot_armory.robot.connection import Connection
from tests.support.cluster import make_planner, one_chunk, replica_config, stale_actions, start_fleet, wait_for


@pytest.fixture(scope="module")
def planner_dir(tmp_path_factory):
    return make_planner(tmp_path_factory.mktemp("planner") / "planner")


@pytest.fixture
def cluster(planner_dir):
    """3 in-process replicas and a front; stopped afterwards."""
    replicas = LocalReplicas({f"r{k}": ArmoryReplica(replica_config(planner_dir), f"r{k}") for k in range(3)})
    front = FrontServer(ClusterFront(replicas, FrontOptions(health_interval_s=0.2)))
    yield front, replicas
    front.stop(0)
    for rid in replicas.ids():
        replicas.kill(rid)


@pytest.mark.slow
def test_robots_are_placed_balanced_and_follow_the_redirect(cluster):
    front, replicas = cluster
    robots = start_fleet(front.address, duration_s=5.0)
    assert wait_for(lambda: len(front.front.placements()) == 6)
    where = front.front.placements()
    per_replica = Counter(where.values())
    assert sorted(per_replica.values()) == [2, 2, 2], where
    # mirror-aware placement spreads the fast robots: one per replica
    fast_per_replica = Counter(rid for robot, rid in where.items() if int(robot[-1]) % 2 == 0)
    assert sorted(fast_per_replica.values()) == [1, 1, 1], where
    stats = [r.join() for r in robots]
    for s in stats:
        assert s["executed_steps"] > 40, s  # every robot was served by its replica
    # each robot streamed to the replica the front named, not to the front
    for r in robots:
        assert r.client.connection is None or r.client.connection.address != front.address


@pytest.mark.slow
def test_a_dead_replica_s_robots_resume_elsewhere_within_3_s_and_never_run_a_stale_action(cluster):
    front, replicas = cluster
    robots = start_fleet(front.address, duration_s=9.0)
    assert wait_for(lambda: len(front.front.placements()) == 6)
    assert wait_for(lambda: all(r.client.executed > 30 for r in robots), timeout=10)  # every robot streaming
    victim = front.front.placements()["robot0"]
    moved = [robot for robot, rid in front.front.placements().items() if rid == victim]
    replicas.kill(victim)
    everyone = {f"robot{k}" for k in range(6)}
    assert wait_for(lambda: set(front.front.placements()) == everyone and victim not in front.front.placements().values())
    stats = {r.client.identity.robot_id: (r, r.join()) for r in robots}
    for robot_id in moved:
        r, s = stats[robot_id]
        assert r.client.reconnects >= 1, s
        assert s["outages_s"] and max(s["outages_s"]) < 3.0, s["outages_s"]
        assert stale_actions(r.client) == []


@pytest.mark.slow
def test_a_restarted_front_loses_no_running_robot(cluster, planner_dir):
    front, replicas = cluster
    robots = start_fleet(front.address, duration_s=7.0)
    assert wait_for(lambda: len(front.front.placements()) == 6)
    before = front.front.placements()
    port = front.port
    front.stop(0)
    executed = [r.client.executed for r in robots]
    # still served, by their replicas, with no front
    assert wait_for(lambda: all(r.client.executed > e + 10 for r, e in zip(robots, executed, strict=True)), timeout=10)
    assert all(r.client.reconnects == 0 for r in robots)
    again = FrontServer(ClusterFront(replicas, FrontOptions(health_interval_s=0.2)), port=port)
    try:
        assert again.front.placements() == before  # the first refresh rebuilt the view from the replicas
        for r in robots:
            r.join()
    finally:
        again.stop(0)


@pytest.mark.slow
def test_a_move_happens_between_chunks_and_costs_the_robot_no_action(cluster):
    front, replicas = cluster
    robots = start_fleet(front.address, n=2, duration_s=6.0)
    assert wait_for(lambda: len(front.front.placements()) == 2)
    assert wait_for(lambda: all(r.client.executed > 20 for r in robots), timeout=10)  # both streaming
    source = front.front.placements()["robot0"]
    target = next(rid for rid in replicas.ids() if rid not in front.front.placements().values())
    from lerobot_armory.placement import Move

    front.front._release(Move("robot0", source, target), time.monotonic())
    assert wait_for(lambda: front.front.placements().get("robot0") == target, timeout=5.0)
    stats = robots[0].join()
    robots[1].join()
    assert robots[0].client.reconnects == 1
    assert stats["outages_s"] == []  # it kept executing the chunks it held while re-registering
    log = robots[0].client.executed_log
    sessions = [e[1] for e in log]
    assert sessions == sorted(sessions) and set(sessions) == {1, 2}  # the first session's chunks ran out, then the second's
    assert any("moved" in n for n in robots[0].client.notices)


def test_the_front_forwards_refusals_and_refuses_streams(cluster):
    front, _ = cluster
    conn = Connection(front.address)
    assert conn.wait_ready(5)
    with pytest.raises(grpc.RpcError) as refused:
        conn.register("bad", {"nope": ("float32", (3,))}, 20.0, 1, 10)
    assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "nope" in refused.value.details()  # the replica's own explanation, passed through
    call = conn.stub.Stream(iter(()))
    with pytest.raises(grpc.RpcError) as streamed:
        list(call)
    assert streamed.value.code() == grpc.StatusCode.FAILED_PRECONDITION
    assert "stream_address" in streamed.value.details()
    conn.close()


def test_a_chunk_through_the_cluster_equals_a_single_server_s(cluster, planner_dir):
    front, _ = cluster
    single = ArmoryReplica(replica_config(planner_dir), "single")
    try:
        via_front, placed_at = one_chunk(front.address)
        alone, direct = one_chunk(single.address)
        assert placed_at != "" and direct == ""  # the front redirected; the single server did not
        np.testing.assert_array_equal(via_front, alone)
    finally:
        single.stop()


@pytest.mark.slow
def test_a_replica_gone_silent_is_detected_by_keepalive_and_its_robot_resumes_elsewhere(planner_dir):
    """No reset, no close: the replica's host just stops answering. gRPC keepalive breaks the
    stream (5 s pings, 3 s timeout) and the robot fails over through the front."""
    from tests.support.cluster import FreezableProxy

    hidden = ArmoryReplica(replica_config(planner_dir), "r0")
    proxy = FreezableProxy(hidden.server.port)
    hidden.address = f"127.0.0.1:{proxy.port}"  # robots and the front reach r0 only through the proxy
    replicas = LocalReplicas({"r0": hidden, "r1": ArmoryReplica(replica_config(planner_dir), "r1")})
    front = FrontServer(ClusterFront(replicas, FrontOptions(health_interval_s=0.2, rebalance=False)))
    try:
        robots = start_fleet(front.address, n=1, duration_s=18.0)
        assert wait_for(lambda: front.front.placements().get("robot0") == "r0", timeout=5)
        assert wait_for(lambda: robots[0].client.executed > 15, timeout=10)  # streaming through r0
        proxy.freeze()
        frozen_at = time.monotonic()
        assert wait_for(lambda: robots[0].client.reconnects >= 1, timeout=14)
        detected = time.monotonic() - frozen_at
        stats = robots[0].join()
        print(f"silent replica: stream broken {detected:.1f} s after the freeze; outage {max(stats['outages_s']):.1f} s")
        assert detected < 12.0, detected
        assert stats["outages_s"] and max(stats["outages_s"]) < 12.0, stats["outages_s"]
        assert stale_actions(robots[0].client) == []
        assert robots[0].client.connection is None or robots[0].client.executed > 200
    finally:
        front.stop(0)
        for rid in replicas.ids():
            replicas.kill(rid)


def test_receipts_of_an_earlier_session_are_not_reported_to_the_next_server():
    """Chunk ids restart with each session: a chunk kept across a move must not be reported to
    the new replica as one of its own (its delay estimate would be wrong)."""
    from lerobot_armory.robot.actions import ActionBuffer

    buf = ActionBuffer(h_max=4)
    buf.session = 1
    buf.add(0, 0, np.zeros((10, 2), np.float32), 0.1)
    buf.action_for(0)  # executed in session 1
    buf.session = 2
    buf.add(0, 2, np.ones((10, 2), np.float32), 0.2)
    buf.action_for(2)
    assert buf.take_receipts(session=2) == [(0, 0.2, 0)]


def test_lying_and_absurd_registrations_are_refused_by_the_replica_and_hurt_nobody(cluster):
    """NaN fps, negative horizons, an absurd weight, a megabyte id: the replica's own refusal comes
    back through the front; the front keeps placing honest robots, and no reservation is left."""
    front, _ = cluster
    conn = Connection(front.address)
    assert conn.wait_ready(5)
    from lerobot_armory.robot.armory_sim import ArmorySim, ArmorySimConfig
    from lerobot_armory.robot.features import FeatureMap

    robot = ArmorySim(ArmorySimConfig(scene="static", image_size=32, seed=0))
    features = FeatureMap.for_robot(robot.observation_features, robot.action_features).wire_features()
    for robot_id, fps, h_min, h_max, weight in [
        ("nan", float("nan"), 1, 10, 1.0),
        ("neg", 20.0, -3, -1, 1.0),
        ("heavy", 20.0, 1, 10, 1e300),
        ("x" * 100_000, 20.0, 1, 10, 1.0),
    ]:
        with pytest.raises(grpc.RpcError) as refused:
            conn.register(robot_id, features, fps, h_min, h_max, weight)
        assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT, (robot_id[:10], refused.value)
    assert all(not s.pending for s in front.front.state.values())  # nothing reserved for the refused
    honest = Connection(front.address)
    reg = honest.register("honest", features, 20.0, 1, 10)
    assert reg.stream_address
    honest.end_session()
    conn.close()


@pytest.mark.subprocess
@pytest.mark.skipif(__import__("shutil").which("openssl") is None, reason="openssl not installed")
def test_with_tls_the_front_and_the_replicas_speak_tls_end_to_end(planner_dir, tmp_path):
    """The front forwards over TLS (trusting the shared certificate), the robot follows the
    redirect with the same trust root, and a plaintext robot is refused at the front."""
    import dataclasses
    import subprocess

    key, cert = tmp_path / "key.pem", tmp_path / "cert.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out", str(cert), "-days", "1",
         "-subj", "/CN=localhost", "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"],
        check=True, capture_output=True,
    )  # fmt: skip
    cfg = dataclasses.replace(replica_config(planner_dir), tls_cert=str(cert), tls_key=str(key))
    replicas = LocalReplicas({f"r{k}": ArmoryReplica(cfg, f"r{k}") for k in range(2)})
    pem = cert.read_bytes()
    channels = lambda address: grpc.secure_channel(address, grpc.ssl_channel_credentials(root_certificates=pem))  # noqa: E731
    front = FrontServer(ClusterFront(replicas, FrontOptions(health_interval_s=0.2), channel_factory=channels),
                        tls=(key.read_bytes(), pem))  # fmt: skip
    try:
        from lerobot_armory.robot.armory_sim import ArmorySim, ArmorySimConfig
        from lerobot_armory.robot.features import FeatureMap

        robot = ArmorySim(ArmorySimConfig(scene="static", image_size=32, seed=0))
        fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
        secure = Connection(f"localhost:{front.port}", tls_ca=pem)
        reg = secure.register("tls-robot", fmap.wire_features(), 20.0, 1, 10)
        assert reg.stream_address and secure.address == reg.stream_address
        got: list = []
        secure.open_stream(got.append)
        robot.connect()
        secure.send_observation(0, fmap.to_wire(robot.get_observation()))
        assert wait_for(lambda: bool(got), timeout=5.0)  # the chunk came over the replica's TLS stream
        secure.close()
        plain = Connection(f"localhost:{front.port}")
        with pytest.raises(grpc.RpcError):
            plain.register("plain", fmap.wire_features(), 20.0, 1, 10, timeout=3)
        plain.close()
    finally:
        front.stop(0)
        for rid in replicas.ids():
            replicas.kill(rid)
