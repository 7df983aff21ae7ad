"""A cluster of several policies (``lerobot-armory-cluster --policies=FILE``): every replica serves
every policy of the file; the front charges each robot its own policy's load on each replica, and
rolls a swap of one policy replica by replica, leaving the others as they are.

The front's bookkeeping is checked on replicas it reads fake load answers from (no model); the
rest on two in-process replicas (:class:`LocalReplicas`) of two tiny ACTs of different state and
action sizes, with the batch times of an H100's pi0.5 emulated: the sorting policy's batch cap is
1, the kitchen's 3, so a sorting robot's chunk costs a whole batch and a kitchen robot's a third
of a larger one.
"""

from __future__ import annotations

import dataclasses
import json
import threading

import grpc
import pytest

from lerobot_armory.engine.options import EngineOptions, PolicyOptions
from lerobot_armory.entrypoints.cluster.cli import ClusterConfig, preflight
from lerobot_armory.entrypoints.cluster.front import PENDING_S, ClusterFront, FrontOptions, FrontServer
from lerobot_armory.entrypoints.cluster.replica import ArmoryReplica, LocalReplicas
from lerobot_armory.entrypoints.server import ServerConfig
from lerobot_armory.errors import ConfigError
from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.placement import Capacity, demand
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import ArmoryAdminStub
from lerobot_armory.proto.limits import TOKEN_KEY
from lerobot_armory.robot.client import ArmoryClient, RobotIdentity
from lerobot_armory.robot.connection import Connection
from lerobot_armory.schedulers import EarliestDeadlineConfig
from lerobot_armory.serving.security import OperatorTokens
from tests.conftest import TINY
from tests.entrypoints.test_multi_policy import KITCHEN, SORTING, _obs
from tests.support.pusher import wait_for

OPERATOR = "operator-token-0123456789abcdef"
ONE_WAY_S = 0.00375

# ---- the front's bookkeeping, on fake load answers ----------------------------------------------

KITCHEN_S = [0.05, 0.07, 0.09]  # d_infer(b), b <= 3
SORTING_S = [0.08]  # b <= 1: a sorting robot's chunk costs a whole batch


class FakeReplicas:
    """Two replicas serving kitchen (main, chunk 10) and sorting (chunk 20); the test says who streams where."""

    def __init__(self) -> None:
        self.robots: dict[str, list[tuple[str, str]]] = {"a": [], "b": []}  # replica -> [(robot, policy)]

    def ids(self) -> list[str]:
        return ["a", "b"]

    def load(self, replica_id, timeout):
        policy = lambda s, chunk, path: {"latency_s": s, "chunk_size": chunk, "description": path, "path": path, "overrides": [], "swaps": {}}  # noqa: E731
        robots = [
            {**dataclasses.asdict(RobotSpec(robot, 20.0, 10, 5, 10)), "starvation_pct": 0.0, "policy": name}
            for robot, name in self.robots[replica_id]
        ]  # fmt: skip
        return {
            "replica_id": replica_id, "address": f"127.0.0.1:{1 if replica_id == 'a' else 2}", "latency_s": KITCHEN_S,
            "max_robots": 64, "chunk_size": 10, "policy": "/k", "policy_path": "/k", "policy_overrides": [], "swaps": {},
            "policy_name": "kitchen", "policies": {"kitchen": policy(KITCHEN_S, 10, "/k"), "sorting": policy(SORTING_S, 20, "/s")},
            "robots": robots, "instance": replica_id, "alive": True, "status": "",
        }  # fmt: skip

    def set_forwarding_key(self, replica_id, key, timeout) -> None:
        pass

    def release(self, replica_id, robot_id, timeout) -> bool:
        return True


def _request(robot_id: str, policy: str) -> pb.RegisterRequest:
    return pb.RegisterRequest(robot_id=robot_id, fps=20.0, h_min=5, h_max=10, weight=1.0, tier="slow", policy_name=policy)


def test_the_front_charges_each_robot_its_own_policy_s_capacity():
    now = [100.0]
    replicas = FakeReplicas()
    replicas.robots = {"a": [("s0", "sorting"), ("s1", "sorting")], "b": [("k0", "kitchen"), ("k1", "kitchen")]}
    front = ClusterFront(replicas, FrontOptions(), clock=lambda: now[0])
    front.refresh()
    # Balanced as it is: a sorting robot moved to b would weigh as much there as on a (0.19 + 0.15
    # against 0.39: not worth a move), not as a kitchen robot of b.
    assert front.moves_made == 0 and front._plan_move(now[0]) is None
    assert front.policy_names() == ("kitchen", "sorting") and front.main == "kitchen"
    assert front.policies == {"kitchen": ("/k", ()), "sorting": ("/s", ())}  # every replica agreed
    sorting, kitchen = Capacity(tuple(SORTING_S), ONE_WAY_S), Capacity(tuple(KITCHEN_S), ONE_WAY_S)
    a, b = front.state["a"].view, front.state["b"].view
    spec = RobotSpec("s0", 20.0, 10, 5, 10)
    # The same timing, the same replica: a sorting robot weighs what a batch of one sorting chunk costs.
    assert a.demand(spec) == demand(spec, sorting) > 2 * demand(spec, kitchen)
    assert a.utilization() == pytest.approx(2 * demand(spec, sorting)) and b.utilization() == pytest.approx(2 * demand(spec, kitchen))
    # A kitchen robot goes where the kitchen robots are: b is lighter once each robot is charged at
    # its own policy (charged alike, a and b would tie and a would win on its name).
    assert next(front.choices(_request("k2", "kitchen"))) == "b"
    assert front.state["b"].pending_policy == {"k2": "kitchen"}
    # A pending sorting robot is charged at sorting's capacity, with sorting's chunk size.
    assert front._spec(_request("s2", "sorting")).chunk_size == 20 and front._spec(_request("k3", "")).chunk_size == 10
    rid = next(front.choices(_request("s2", "sorting")))
    state = front.state[rid]
    assert state.pending_policy["s2"] == "sorting"
    assert state.view.demand(state.view.robots["s2"]) == demand(state.view.robots["s2"], sorting)
    # A robot naming a policy nobody serves (the replica will refuse it) is charged at the main
    # policy's; one naming none too (the main policy's robots on a single-policy cluster).
    assert front.policy_for("bakery") == front.policy_for("") == "kitchen"
    rid = next(front.choices(_request("lost", "bakery")))
    assert front.state[rid].pending_policy["lost"] == "kitchen"
    assert front.state[rid].view.demand(front.state[rid].view.robots["lost"]) == demand(front.state[rid].view.robots["lost"], kitchen)
    # Bounded: once the replicas report, or the reservation lapses, the front keeps no robot's policy
    # but those the replicas report.
    replicas.robots["b"].append(("k2", "kitchen"))
    now[0] += PENDING_S + 1
    front.refresh()
    assert all(not s.pending and not s.pending_policy for s in front.state.values())
    assert front.state["b"].reported_policy == {"k0": "kitchen", "k1": "kitchen", "k2": "kitchen"}
    assert front.policy_of == {"s0": "sorting", "s1": "sorting", "k0": "kitchen", "k1": "kitchen", "k2": "kitchen"}


# ---- two replicas of two tiny ACTs ------------------------------------------------------------


@pytest.fixture(scope="module")
def two_policy_cluster(tmp_path_factory):
    """2 in-process replicas serving kitchen (b <= 3) and sorting (b <= 1), and a front with an operator token."""
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

    root = tmp_path_factory.mktemp("two")
    make_demo_policy(DemoPolicyConfig(output=str(root / "kitchen"), **TINY))
    make_demo_policy(DemoPolicyConfig(output=str(root / "sorting"), **{**TINY, "state_dim": 3, "seed": 1}))
    policies = root / "policies.json"
    policies.write_text(json.dumps({"kitchen": {"path": str(root / "kitchen")}, "sorting": {"path": str(root / "sorting"), "max_batch_size": 1}}))
    cfg = ServerConfig(
        policy=PolicyOptions(device="cpu", cpu_threads=1), policies=str(policies), engine=EngineOptions(emulate_profile="h100-pi05"),
        scheduler=EarliestDeadlineConfig(), max_batch_size=3, status_interval_s=0.0, log_level="warning", port=0,
    )  # fmt: skip
    replicas = LocalReplicas({f"r{k}": ArmoryReplica(cfg, f"r{k}") for k in range(2)})
    front = FrontServer(ClusterFront(replicas, FrontOptions(health_interval_s=0.2, rebalance=False)), operators=OperatorTokens([OPERATOR]))
    yield front, replicas, cfg, root
    front.stop(0)
    for rid in replicas.ids():
        replicas.kill(rid)


def _client(address: str, robot_id: str, policy: str, got: dict[str, set[int]]) -> ArmoryClient:
    features = KITCHEN if policy == "kitchen" else SORTING
    obs = _obs(features)
    got[robot_id] = set()
    return ArmoryClient(
        address, RobotIdentity(robot_id, 20.0, 2, 10, policy_name=policy), features,
        observe=lambda: obs, act=lambda a: got[robot_id].add(len(a)),
    )  # fmt: skip


def _run(clients: list[ArmoryClient], seconds: float) -> list[threading.Thread]:
    threads = [threading.Thread(target=c.run, args=(seconds,), daemon=True) for c in clients]
    for t in threads:
        t.start()
    return threads


@pytest.mark.slow
def test_robots_of_two_policies_stream_through_the_front_each_charged_at_its_own_policy(two_policy_cluster):
    front, replicas, _, _ = two_policy_cluster
    info = replicas.replicas["r0"].info()
    assert info["policy_name"] == "kitchen" and list(info["policies"]) == ["kitchen", "sorting"]
    assert len(info["policies"]["kitchen"]["latency_s"]) == 3 and len(info["policies"]["sorting"]["latency_s"]) == 1
    assert info["latency_s"] == info["policies"]["kitchen"]["latency_s"]  # the top level: the main policy's
    assert wait_for(lambda: front.front.policy_names() == ("kitchen", "sorting"), timeout=5)
    got: dict[str, set[int]] = {}
    clients = [_client(front.address, name, policy, got) for name, policy in (("k0", "kitchen"), ("k1", "kitchen"), ("s0", "sorting"), ("s1", "sorting"))]
    threads = _run(clients, 4.0)
    try:
        assert wait_for(lambda: len(front.front.placements()) == 4 and all(c.chunks_received >= 3 for c in clients), timeout=20)
        # Each replica reports its robots' policies; the front charges each robot at its own.
        reported = {r["robot_id"]: r["policy"] for rid in replicas.ids() for r in replicas.replicas[rid].load()["robots"]}
        assert reported == {"k0": "kitchen", "k1": "kitchen", "s0": "sorting", "s1": "sorting"}
        assert wait_for(lambda: sum(len(s.reported) for s in front.front.state.values()) == 4, timeout=5)
        with front.front.lock:
            charged = {}
            for state in front.front.state.values():
                for robot, spec in state.reported.items():
                    charged[robot] = state.view.demand(spec)
                    assert charged[robot] == demand(spec, state.capacities[reported[robot]]), robot
        # The four robots ask for the same timing: a sorting robot weighs more (b <= 1 and its chunk costs a whole batch).
        assert min(charged["s0"], charged["s1"]) > 1.5 * max(charged["k0"], charged["k1"]), charged
    finally:
        for t in threads:
            t.join(timeout=30)
        for c in clients:
            c.close()
    # Each robot executed its own policy's actions: 2 dims in the kitchen, 3 in the sorting cell.
    assert got["k0"] == got["k1"] == {2} and got["s0"] == got["s1"] == {3}, got
    for policy in ("kitchen", "sorting"):
        assert sum(replicas.replicas[rid].server.loop.stats.batches_by_policy[policy] for rid in replicas.ids()) > 0


def test_a_robot_naming_an_unknown_policy_is_refused_in_one_line_through_the_front(two_policy_cluster):
    front, _, _, _ = two_policy_cluster
    conn = Connection(front.address)
    try:
        with pytest.raises(grpc.RpcError) as err:
            conn.register("r-bakery", KITCHEN, 10.0, 1, 5, policy_name="bakery")
    finally:
        conn.close()
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "no policy named 'bakery'" in err.value.details() and "'kitchen', 'sorting'" in err.value.details()
    assert len(err.value.details().splitlines()) == 1
    assert all("r-bakery" not in s.pending and not s.pending_policy.get("r-bakery") for s in front.front.state.values())


def _admin(address: str):
    stub = ArmoryAdminStub(grpc.insecure_channel(address))
    md = ((TOKEN_KEY, OPERATOR),)
    swap = lambda path, name: stub.SwapPolicy(pb.SwapRequest(policy_path=str(path), policy_name=name), metadata=md, timeout=120)  # noqa: E731
    status = lambda: stub.Status(pb.AdminStatusRequest(), metadata=md, timeout=10)  # noqa: E731
    return swap, status


@pytest.mark.slow
def test_a_rolling_swap_of_one_policy_leaves_the_other_on_every_replica(two_policy_cluster):
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

    front, replicas, cfg, root = two_policy_cluster
    new = root / "sorting-v2"
    make_demo_policy(DemoPolicyConfig(output=str(new), **{**TINY, "state_dim": 3, "seed": 2}))
    swap, status = _admin(front.address)
    # A name the cluster does not serve, or none on a cluster of several: refused in one line.
    for name, why in (("bakery", "no policy named 'bakery'"), ("", "serves several policies")):
        with pytest.raises(grpc.RpcError) as err:
            swap(new, name)
        assert err.value.code() == grpc.StatusCode.NOT_FOUND and why in err.value.details(), err.value.details()
        assert "'kitchen', 'sorting'" in err.value.details() and len(err.value.details().splitlines()) == 1
    kitchen_engines = {rid: replicas.replicas[rid].server.loop.policies["kitchen"].engine for rid in replicas.ids()}
    got: dict[str, set[int]] = {}
    clients = [_client(front.address, "k9", "kitchen", got), _client(front.address, "s9", "sorting", got)]
    threads = _run(clients, 6.0)
    try:
        assert wait_for(lambda: all(c.chunks_received >= 3 for c in clients), timeout=20)
        reply = swap(new, "sorting")
        assert reply.result == "ok", reply.message
        assert reply.message == f"r0,r1 serve sorting={new}" and reply.old_path == str(root / "sorting"), reply
        counts = [c.chunks_received for c in clients]
        assert wait_for(lambda: all(c.chunks_received >= n + 3 for c, n in zip(clients, counts, strict=True)), timeout=20)
    finally:
        for t in threads:
            t.join(timeout=30)
        for c in clients:
            c.close()
    assert got == {"k9": {2}, "s9": {3}}
    for rid in replicas.ids():
        server = replicas.replicas[rid].server
        assert server.swappers["sorting"].current.path == str(new)
        assert server.swappers["kitchen"].current.path == str(root / "kitchen")
        assert server.loop.policies["kitchen"].engine is kitchen_engines[rid]  # never swapped
        assert len(server.loop.policies["sorting"].scheduler.d_infer) == 1  # its own cap, not kitchen's
    assert front.front.policies == {"kitchen": (str(root / "kitchen"), ()), "sorting": (str(new), ())}
    # Status: the main policy's path where there is room for one, every policy's in the lines.
    s = status()
    assert s.policy_path == str(root / "kitchen") and s.swaps_ok == 1
    assert s.policy == f"cluster policies: kitchen={root / 'kitchen'}, sorting={new}"
    assert wait_for(lambda: all(r.swaps_ok == 1 for r in status().replicas), timeout=5)
    s = status()
    assert [r.policy_path for r in s.replicas] == [str(root / "kitchen")] * 2
    assert f"r0 serves kitchen={root / 'kitchen'}, sorting={new}; r1 serves kitchen={root / 'kitchen'}, sorting={new}" in s.status_line
    # A replica that restarts (as Ray would: with the options the cluster started with) is brought
    # to every policy the cluster remembers before robots are placed on it: sorting swapped, kitchen left.
    replicas.kill("r0")
    replicas.replicas["r0"] = ArmoryReplica(cfg, "r0")
    restarted = replicas.replicas["r0"].server
    kitchen = restarted.loop.policies["kitchen"].engine
    assert restarted.swappers["sorting"].current.path == str(root / "sorting")
    assert wait_for(lambda: restarted.swappers["sorting"].current.path == str(new), timeout=30)
    assert wait_for(lambda: front.front.state["r0"].view.healthy, timeout=5)
    assert restarted.loop.policies["kitchen"].engine is kitchen and restarted.swappers["kitchen"].counts.by_result["ok"] == 0


def test_a_cluster_takes_a_policies_file_and_a_bad_one_is_one_line(tmp_path):
    good = tmp_path / "policies.yaml"
    good.write_text("kitchen:\n  path: /m/kitchen\nsorting:\n  path: /m/sorting\n  max_batch_size: 2\n")
    cfg = ClusterConfig(policies=str(good), replicas=2)
    preflight(cfg)  # no refusal: a cluster serves several policies
    assert cfg.replica_config().policies == str(good)
    assert cfg.served() == "kitchen=/m/kitchen, sorting=/m/sorting"
    bad = tmp_path / "bad.yaml"
    bad.write_text("kitchen:\n  path: /m/kitchen\n  colour: blue\n")
    with pytest.raises(ConfigError, match="policies") as err:
        preflight(ClusterConfig(policies=str(bad)))
    assert "unknown key(s) colour" in str(err.value) and len(str(err.value).splitlines()) == 1
    with pytest.raises(ConfigError, match="not both"):
        preflight(ClusterConfig(policies=str(good), policy=PolicyOptions("x")))


def test_replicas_serving_different_policies_are_warned_of_once(caplog):
    class Uneven(FakeReplicas):
        def load(self, replica_id, timeout):
            answer = super().load(replica_id, timeout)
            if replica_id == "b":  # b was started without the sorting policy
                answer["policies"] = {"kitchen": answer["policies"]["kitchen"]}
            return answer

    front = ClusterFront(Uneven(), FrontOptions())
    with caplog.at_level("WARNING", logger="lerobot_armory.entrypoints.cluster.front"):
        front.refresh()
        front.refresh()
    warned = [r.getMessage() for r in caplog.records if "serve different policies" in r.getMessage()]
    assert warned == ["the replicas serve different policies (a: kitchen, sorting; b: kitchen): a robot of a policy its replica lacks is refused there"]
    assert front.policy_names() == ("kitchen", "sorting")
    caplog.clear()
    with caplog.at_level("WARNING", logger="lerobot_armory.entrypoints.cluster.front"):
        ClusterFront(FakeReplicas(), FrontOptions()).refresh()  # alike: nothing to say
    assert not [r for r in caplog.records if "serve different policies" in r.getMessage()]


def test_replicas_serving_one_name_from_different_checkpoints_are_warned_of_once_but_not_during_a_roll(caplog):
    """A front restarted beside replicas that serve ``kitchen`` from two checkpoints (one left from
    another cluster): the names agree, so nothing is refused, but a robot's chunks would depend on
    its replica — said once, with the paths. While a roll or catch-up holds the roll lock the
    checkpoints differ on purpose: nothing is said."""

    class Mixed(FakeReplicas):
        def load(self, replica_id, timeout):
            answer = super().load(replica_id, timeout)
            if replica_id == "b":
                answer["policies"] = {**answer["policies"], "kitchen": {**answer["policies"]["kitchen"], "path": "/k2"}}
            return answer

    logger = "lerobot_armory.entrypoints.cluster.front"
    rolling = ClusterFront(Mixed(), FrontOptions())
    with caplog.at_level("WARNING", logger=logger):
        with rolling._roll_lock:
            rolling.refresh()
    assert not [r for r in caplog.records if "different checkpoints" in r.getMessage()]
    front = ClusterFront(Mixed(), FrontOptions())
    with caplog.at_level("WARNING", logger=logger):
        front.refresh()
        front.refresh()
    warned = [r.getMessage() for r in caplog.records if "different checkpoints" in r.getMessage()]
    assert warned == [
        "the replicas serve different checkpoints under one name (a: kitchen=/k, sorting=/s; b: kitchen=/k2, sorting=/s): "
        "a robot's chunks depend on its replica; lerobot-armory-admin swap --policy_name=NAME brings them to one"
    ]
    assert front.policy_names() == ("kitchen", "sorting")
