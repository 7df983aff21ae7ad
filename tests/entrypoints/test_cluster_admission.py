"""Admission through the cluster front: registrations that never stream cannot lock the cluster,
and the front's refusals say the true reason (full, not "no replica is up"), counted and published
on the front's Prometheus endpoint."""

from __future__ import annotations

import urllib.request

import grpc
import pytest
from prometheus_client.parser import text_string_to_metric_families

from lerobot_armory.entrypoints.cluster.front import ClusterFront, FrontOptions, FrontServer
from lerobot_armory.entrypoints.cluster.replica import ArmoryReplica, LocalReplicas, ReplicaDown
from lerobot_armory.serving.admission import AdmissionLimiter
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


def _scrape(port: int) -> dict[tuple[str, tuple], float]:
    """The front's metrics endpoint as {(sample name, sorted labels): value}."""
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5).read().decode()
    return {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
    }


def _refused(metrics: dict, reason: str) -> float:
    return metrics[("armory_front_registrations_refused_total", (("reason", reason),))]


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
    metrics = _scrape(front.serve_metrics(0))
    assert sum(v for (name, _), v in metrics.items() if name == "armory_front_registrations_placed_total") == 13
    assert all(_refused(metrics, reason) == 0 for reason in ("rate", "replica_rate", "full", "unavailable", "down"))
    assert metrics[("armory_front_replica_up", (("replica", "r0"),))] == 1.0
    assert metrics[("armory_front_replica_max_robots", (("replica", "r1"),))] == 2.0


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
        metrics = _scrape(front.serve_metrics(0))
        assert _refused(metrics, "full") == 1 and _refused(metrics, "down") == 0
        assert sum(metrics[("armory_front_replica_robots", (("replica", rid),))] for rid in ("r0", "r1")) == 4
    finally:
        for r in robots:
            r.client.close()


def test_a_replica_s_registration_limit_is_named_as_such_not_as_full_replicas(small_cluster):
    """Every registration reaches a replica from the front's host, so the replicas' per-host limit
    counts all the front's robots together; when it refuses, the front says so (replica_rate)."""
    front, local = small_cluster
    assert wait_for(lambda: all(s.view.healthy for s in front.front.state.values()), timeout=10)
    for rid in local.ids():
        local.replicas[rid].server.service.admission = AdmissionLimiter(peer_rate_hz=0.01, peer_burst=2)
    answers = [_register(front.address, f"r{k}") for k in range(5)]
    assert answers[:4] == ["OK"] * 4, answers
    assert answers[4].startswith("RESOURCE_EXHAUSTED: the replicas take no more registrations through this front"), answers[4]
    assert "too many registrations from this host (127.0.0.1)" in answers[4] and "full of robots" not in answers[4]
    assert front.front.refused["replica_rate"] == 1 and front.front.refused["full"] == 0
    assert _refused(_scrape(front.serve_metrics(0)), "replica_rate") == 1


class DeadReplicas:
    """Two replicas that never answer."""

    def ids(self) -> list[str]:
        return ["a", "b"]

    def load(self, replica_id, timeout):
        raise ReplicaDown(replica_id)

    def release(self, replica_id, robot_id, timeout) -> bool:
        raise ReplicaDown(replica_id)


def test_refusals_are_published_by_reason_on_the_front_s_metrics_port():
    front = FrontServer(ClusterFront(DeadReplicas(), FrontOptions(health_interval_s=5.0)))
    front.front.admission = AdmissionLimiter(peer_rate_hz=0.01, peer_burst=3)
    try:
        port = front.serve_metrics(0)
        before = _scrape(port)
        assert all(_refused(before, reason) == 0 for reason in ("rate", "replica_rate", "full", "unavailable", "down"))
        answers = [_register(front.address, f"r{k}") for k in range(5)]
        assert [a.split(":")[0] for a in answers] == ["UNAVAILABLE"] * 3 + ["RESOURCE_EXHAUSTED"] * 2, answers
        assert "no replica is up" in answers[0] and "too many registrations" in answers[3]
        after = _scrape(port)
        assert _refused(after, "down") == 3 and _refused(after, "rate") == 2 and _refused(after, "full") == 0
        assert after[("armory_front_replica_up", (("replica", "a"),))] == 0.0
        assert after[("armory_front_moves_total", ())] == 0
    finally:
        front.stop(0)
