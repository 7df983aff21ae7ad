"""Admission through the cluster front: registrations that never stream cannot lock the cluster,
and the front's refusals say the true reason (full, not "no replica is up"), counted."""

from __future__ import annotations

import grpc
import pytest

from lerobot_armory.entrypoints.cluster.front import ClusterFront, FrontOptions, FrontServer
from lerobot_armory.entrypoints.cluster.replica import ArmoryReplica, LocalReplicas
from lerobot_armory.robot.connection import Connection
from tests.support.cluster import IMAGE, make_planner, replica_config, sim_robot, wait_for

FEATURES = {"observation.state": ("float32", (2,)), "observation.images.front": ("uint8", (IMAGE, IMAGE, 3))}


@pytest.fixture
def small_cluster(tmp_path):
    """2 in-process replicas with room for 2 robots each, and a front."""
    planner = make_planner(tmp_path / "planner")
    replicas = {}
    for k in range(2):
        cfg = replica_config(planner)
        cfg.max_robots = 2
        replicas[f"r{k}"] = ArmoryReplica(cfg, f"r{k}")
    local = LocalReplicas(replicas)
    front = FrontServer(ClusterFront(local, FrontOptions(health_interval_s=0.2)))
    yield front, local
    front.stop(0)
    for rid in local.ids():
        local.kill(rid)


def _register(address: str, robot_id: str) -> str:
    conn = Connection(address)
    try:
        conn.register(robot_id, FEATURES, 20.0, 1, 10)
        return "OK"
    except grpc.RpcError as exc:
        return f"{exc.code().name}: {exc.details()}"
    finally:
        conn.close()


def test_registrations_that_never_stream_cannot_lock_the_cluster(small_cluster):
    front, _ = small_cluster
    assert wait_for(lambda: all(s.view.healthy for s in front.front.state.values()), timeout=10)
    squats = [_register(front.address, f"squat-{k}") for k in range(12)]  # 3x the cluster's slots, never streamed
    assert squats.count("OK") == 12, squats
    assert _register(front.address, "honest-newcomer") == "OK"  # a replica drops its oldest squatter for it
    assert front.front.refused["down"] == 0


def test_a_cluster_full_of_robots_that_ask_refuses_with_the_true_reason(small_cluster):
    front, _ = small_cluster
    assert wait_for(lambda: all(s.view.healthy for s in front.front.state.values()), timeout=10)
    robots = [sim_robot(front.address, f"robot{k}", fast=False, seed=k) for k in range(4)]
    try:
        for r in robots:
            r.start(20.0)
        assert wait_for(lambda: sum(len(s.reported) for s in front.front.state.values()) == 4, timeout=15)
        answer = _register(front.address, "one-too-many")
        assert answer.startswith("RESOURCE_EXHAUSTED: every replica is full of robots that ask"), answer
        assert "no replica is up" not in answer
        assert front.front.refused["full"] == 1
    finally:
        for r in robots:
            r.client.close()
