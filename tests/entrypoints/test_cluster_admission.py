"""Admission through the cluster front: registrations that never stream cannot lock the cluster,
the front's refusals say the true reason (full, not "no replica is up"), counted and published
on the front's Prometheus endpoint, and the replicas count registrations per robot host, which
the front proves with its forwarding key (a robot cannot name a host of its choosing)."""

from __future__ import annotations

import base64
import logging
import secrets
import urllib.request

import grpc
import pytest
from prometheus_client.parser import text_string_to_metric_families

from lerobot_armory.entrypoints.cluster.front import ClusterFront, FrontOptions, FrontServer
from lerobot_armory.entrypoints.cluster.replica import ArmoryReplica, LocalReplicas, ReplicaDown
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import ArmoryStub
from lerobot_armory.proto.limits import FORWARD_PROOF_KEY, FORWARDED_FOR_KEY
from lerobot_armory.serving.admission import AdmissionLimiter
from lerobot_armory.serving.forwarding import ForwardingKey
from lerobot_armory.robot.connection import Connection
from tests.support.cluster import IMAGE, make_planner, register_from, replica_config, sim_robot, wait_for

FEATURES = {"observation.state": ("float32", (2,)), "observation.images.front": ("uint8", (IMAGE, IMAGE, 3))}
SECRET = secrets.token_bytes(32)  # a front's forwarding key, known here to look for it in logs


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
    """A replica's own per-host limit (here on the robots' host, 127.0.0.1, which the front proves)
    can refuse what the front let through; the front then says so (replica_rate)."""
    front, local = small_cluster
    assert wait_for(lambda: all(s.view.healthy for s in front.front.state.values()), timeout=10)
    for rid in local.ids():
        local.replicas[rid].server.registrar.admission = AdmissionLimiter(peer_rate_hz=0.01, peer_burst=2)
    answers = [_register(front.address, f"r{k}") for k in range(5)]
    assert answers[:4] == ["OK"] * 4, answers
    assert answers[4].startswith("RESOURCE_EXHAUSTED: the replicas take no more registrations through this front"), answers[4]
    assert "too many registrations from this host (127.0.0.1)" in answers[4] and "full of robots" not in answers[4]
    assert front.front.refused["replica_rate"] == 1 and front.front.refused["full"] == 0
    assert _refused(_scrape(front.serve_metrics(0)), "replica_rate") == 1


def _request(robot_id: str) -> pb.RegisterRequest:
    features = [pb.TensorSpec(name=n, dtype=d, shape=list(s)) for n, (d, s) in FEATURES.items()]
    return pb.RegisterRequest(robot_id=robot_id, fps=20.0, h_min=1, h_max=10, weight=1.0, tier="slow", features=features)


def _register_from(front: ClusterFront, host: str, robot_id: str) -> str:
    """Register ``robot_id`` with the front as a robot at ``host`` would: "OK" or "CODE: details"."""
    return register_from(front, host, _request(robot_id))


def _register_direct(stub: ArmoryStub, robot_id: str, metadata: tuple) -> str:
    """Register ``robot_id`` straight with a replica, with ``metadata``: "OK" or "CODE: details"."""
    try:
        stub.Register(_request(robot_id), timeout=5, metadata=metadata)
        return "OK"
    except grpc.RpcError as exc:
        return f"{exc.code().name}: {exc.details()}"


def _keyed(front: FrontServer) -> bool:
    return all(s.view.healthy and s.keyed for s in front.front.state.values())


def test_registrations_from_many_hosts_through_the_front_count_per_robot_host_on_the_replicas(small_cluster):
    """Before the forwarding key every registration through the front counted against the front's
    host on the replicas: their limit (here 2 each) refused the 5th robot whatever its host."""
    front, local = small_cluster
    assert wait_for(lambda: _keyed(front), timeout=10), front.front.describe()
    for rid in local.ids():
        assert local.replicas[rid].server.service.forwarding is not None  # handed by the front
        local.replicas[rid].server.registrar.admission = AdmissionLimiter(peer_rate_hz=0.01, peer_burst=2)
    answers = [_register_from(front.front, f"10.0.0.{k}", f"robot-{k}") for k in range(12)]
    assert answers == ["OK"] * 12, answers
    assert front.front.refused["replica_rate"] == 0
    # One host past the replicas' burst (1 of 2 spent on one replica, 2 left on the other) is
    # refused by them, as that host: the limit per host holds, per robot host.
    again = [_register_from(front.front, "10.0.0.1", f"again-{k}") for k in range(4)]
    assert again[:3] == ["OK"] * 3, again
    assert again[3].startswith("RESOURCE_EXHAUSTED: the replicas take no more registrations through this front"), again[3]
    assert "too many registrations from this host (10.0.0.1)" in again[3], again[3]
    assert _register_from(front.front, "10.0.0.99", "newcomer") == "OK"


def test_a_forwarded_host_without_the_front_s_proof_counts_against_the_real_peer(small_cluster):
    front, local = small_cluster
    assert wait_for(lambda: _keyed(front), timeout=10), front.front.describe()
    replica = local.replicas["r0"]
    replica.server.registrar.admission = AdmissionLimiter(peer_rate_hz=0.01, peer_burst=2)
    channel = grpc.insecure_channel(replica.address)
    stub = ArmoryStub(channel)
    key = front.front.forwarding
    try:
        forged = [
            ("f-0", ((FORWARDED_FOR_KEY, "10.9.9.0"),)),  # no proof
            ("f-1", ((FORWARDED_FOR_KEY, "10.9.9.1"), (FORWARD_PROOF_KEY, "0" * 64))),  # made up
            ("f-2", ((FORWARDED_FOR_KEY, "10.9.9.2"), (FORWARD_PROOF_KEY, ForwardingKey.generate().proof("10.9.9.2", "f-2")))),
            ("f-3", ((FORWARDED_FOR_KEY, "10.9.9.3"), (FORWARD_PROOF_KEY, key.proof("10.9.9.3", "someone-else")))),  # replayed
            ("f-4", ((FORWARDED_FOR_KEY, "10.9.9.4"), (FORWARD_PROOF_KEY, key.proof("10.9.9.5", "f-4")))),  # another host's
        ]
        answers = [_register_direct(stub, robot_id, metadata) for robot_id, metadata in forged]
        assert answers[:2] == ["OK", "OK"], answers  # the burst of 2, spent by the real peer
        for answer in answers[2:]:
            assert answer.startswith("RESOURCE_EXHAUSTED: too many registrations from this host (127.0.0.1)"), answers
        # The control: the front's proof for the host it names is what counts that host instead.
        good = ((FORWARDED_FOR_KEY, "10.9.9.6"), (FORWARD_PROOF_KEY, key.proof("10.9.9.6", "f-6")))
        assert _register_direct(stub, "f-6", good) == "OK"
    finally:
        channel.close()


def test_a_replica_that_restarts_is_handed_the_key_again(small_cluster, tmp_path):
    """A restarted replica is a new instance without a key: the front hands it its key before
    placing robots there (until then it would count them all against the front's host)."""
    front, local = small_cluster
    assert wait_for(lambda: _keyed(front), timeout=10), front.front.describe()
    cfg = replica_config(str(tmp_path / "planner"))  # the fixture's planner
    cfg.max_robots = 2
    local.kill("r0")
    local.replicas["r0"] = ArmoryReplica(cfg, "r0")
    assert local.replicas["r0"].server.service.forwarding is None
    assert wait_for(lambda: _keyed(front) and local.replicas["r0"].server.service.forwarding is not None, timeout=10)
    for rid in local.ids():
        local.replicas[rid].server.registrar.admission = AdmissionLimiter(peer_rate_hz=0.01, peer_burst=1)
    assert [_register_from(front.front, f"10.0.1.{k}", f"robot-{k}") for k in range(6)] == ["OK"] * 6


def test_the_forwarding_key_is_in_no_log_line_answer_or_metric(small_cluster, caplog):
    """A front started again over running replicas hands them its own key (they took the first
    front's), and neither it nor they write it anywhere: logs (at DEBUG) of the handing, of
    refused registrations and of a forger, the refusals' text, the front's metrics."""
    first, local = small_cluster
    assert wait_for(lambda: _keyed(first), timeout=10), first.front.describe()
    first.stop(0)
    for rid in local.ids():
        local.replicas[rid].server.registrar.admission = AdmissionLimiter(peer_rate_hz=0.01, peer_burst=1)
    # A connection of its own (gRPC shares one between channels to the same address): the replica
    # logs once per peer per 10 s, and the front's connection is logged below.
    channel = grpc.insecure_channel(local.replicas["r0"].address, options=[("grpc.use_local_subchannel_pool", 1)])
    front = None
    try:
        with caplog.at_level(logging.DEBUG):
            front = FrontServer(ClusterFront(local, FrontOptions(health_interval_s=0.2), forwarding=ForwardingKey(SECRET)))
            assert wait_for(lambda: _keyed(front), timeout=10), front.front.describe()
            proof = ForwardingKey(SECRET).proof("h", "r")
            assert all(local.replicas[rid].server.service.forwarding.verify("h", "r", proof) for rid in local.ids())
            # One robot host past the replicas' limit: refused by both (the front's line, and theirs).
            answers = [_register_from(front.front, "10.0.0.7", f"k-{k}") for k in range(3)]
            # A forger straight at r0: counted against 127.0.0.1 there (and logged), so its second is refused.
            forged = ((FORWARDED_FOR_KEY, "10.0.0.8"), (FORWARD_PROOF_KEY, "f" * 64))
            answers += [_register_direct(ArmoryStub(channel), f"forger-{k}", forged) for k in range(2)]
            # Robots on 127.0.0.1 over real gRPC: r0's token for that host is spent, r1's is left.
            answers += [_register(front.address, f"over-grpc-{k}") for k in range(2)]
            published = urllib.request.urlopen(f"http://127.0.0.1:{front.serve_metrics(0)}/metrics", timeout=5).read().decode()
            described = front.front.describe() + repr(front.front.forwarding)
    finally:
        channel.close()
        if front is not None:
            front.stop(0)
    assert answers[:2] == ["OK", "OK"] and answers[2].startswith("RESOURCE_EXHAUSTED: the replicas take no more registrations"), answers
    assert answers[3] == "OK" and answers[4].startswith("RESOURCE_EXHAUSTED: too many registrations from this host (127.0.0.1)"), answers
    assert answers[5] == "OK" and answers[6].startswith("RESOURCE_EXHAUSTED: the replicas take no more registrations"), answers
    logged = caplog.text
    assert "registration refused" in logged  # the front's line about its refusal
    assert "without the front's proof" in logged  # the replica's line about the forger
    seen = "\n".join([logged, *answers, published, described])
    for shape in (SECRET.hex(), SECRET.hex().upper(), repr(SECRET), base64.b64encode(SECRET).decode(), SECRET.decode("latin-1")):
        assert shape not in seen


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
