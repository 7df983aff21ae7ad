"""Two policies served to one fleet from one process (``--policies=FILE``): robots name theirs at
registration, are checked against its features, and get its chunks; each batch holds one
policy's robots; a swap of one policy leaves the other serving."""

from __future__ import annotations

import json
import threading

import grpc
import numpy as np
import pytest

from lerobot_armory.engine.options import EngineOptions, PolicyOptions
from lerobot_armory.entrypoints.server import ServerConfig, build_server
from lerobot_armory.errors import ConfigError
from lerobot_armory.robot.client import ArmoryClient, RobotIdentity
from lerobot_armory.robot.connection import Connection
from lerobot_armory.schedulers import EarliestDeadlineConfig
from lerobot_armory.serving.policies_file import load_policies, policies_from_dict
from tests.conftest import TINY

KITCHEN = {"observation.state": ("float32", (2,)), "observation.images.front": ("uint8", (32, 32, 3))}
SORTING = {"observation.state": ("float32", (3,)), "observation.images.front": ("uint8", (32, 32, 3))}


@pytest.fixture(scope="module")
def two_policy_server(tmp_path_factory):
    """A server of two tiny ACTs of different state and action sizes, from one policies file."""
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

    root = tmp_path_factory.mktemp("two")
    make_demo_policy(DemoPolicyConfig(output=str(root / "kitchen"), **TINY))
    make_demo_policy(DemoPolicyConfig(output=str(root / "sorting"), **{**TINY, "state_dim": 3, "seed": 1}))
    policies = root / "policies.json"
    policies.write_text(json.dumps({"kitchen": {"path": str(root / "kitchen")}, "sorting": {"path": str(root / "sorting"), "max_batch_size": 2}}))
    cfg = ServerConfig(
        policy=PolicyOptions(device="cpu", cpu_threads=1), policies=str(policies), engine=EngineOptions(),
        scheduler=EarliestDeadlineConfig(), max_batch_size=3, status_interval_s=0.0, log_level="warning", port=0, profile_reps=2,
    )  # fmt: skip
    server, summary = build_server(cfg)
    records = []
    server.batch_listeners.append(records.append)
    yield server, summary, records, root
    server.stop()


def _obs(features):
    rng = np.random.default_rng(0)
    return {n: (rng.integers(0, 255, s, dtype=np.uint8) if d == "uint8" else rng.standard_normal(s).astype(d)) for n, (d, s) in features.items()}


def test_a_robot_must_name_a_served_policy_and_send_its_features(two_policy_server):
    server, summary, _, _ = two_policy_server
    assert "kitchen" in summary and "sorting" in summary
    conn = Connection(server.address)
    try:
        with pytest.raises(grpc.RpcError) as unnamed:
            conn.register("r-unnamed", KITCHEN, 10.0, 1, 5)
        assert unnamed.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "name one" in unnamed.value.details()
        with pytest.raises(grpc.RpcError) as unknown:
            conn.register("r-unknown", KITCHEN, 10.0, 1, 5, policy_name="bakery")
        assert "no policy named 'bakery'" in unknown.value.details() and "'kitchen', 'sorting'" in unknown.value.details()
        with pytest.raises(grpc.RpcError) as wrong:  # kitchen's features, sorting's policy
            conn.register("r-wrong", KITCHEN, 10.0, 1, 5, policy_name="sorting")
        assert wrong.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "observation.state" in wrong.value.details()
        reg = conn.register("r-ok", SORTING, 10.0, 1, 5, policy_name="sorting")
        assert reg.action_dim == 3
    finally:
        conn.close()


@pytest.mark.slow
def test_two_policies_serve_one_fleet_each_batch_of_one_policy(two_policy_server):
    server, _, records, _ = two_policy_server
    got: dict[str, set[int]] = {}
    clients = []
    for name, features, policy in [("k0", KITCHEN, "kitchen"), ("k1", KITCHEN, "kitchen"), ("s0", SORTING, "sorting"), ("s1", SORTING, "sorting")]:
        obs = _obs(features)
        got[name] = set()
        clients.append(
            ArmoryClient(
                server.address, RobotIdentity(name, 20.0, 2, 10, policy_name=policy), features,
                observe=lambda obs=obs: obs, act=lambda a, name=name: got[name].add(len(a)),
            )  # fmt: skip
        )
    start = len(records)
    threads = [threading.Thread(target=c.run, args=(3.0,)) for c in clients]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for c in clients:
        c.close()
    for c in clients:
        assert c.chunks_received > 5, (c.identity.robot_id, c.chunks_received, c.notices)
    # Each robot executed its own policy's actions: 2 dims in the kitchen, 3 in the sorting cell.
    assert got["k0"] == got["k1"] == {2} and got["s0"] == got["s1"] == {3}
    batches = records[start:]
    assert {r.policy for r in batches} == {"kitchen", "sorting"}
    for r in batches:
        assert {robot[0] for robot in r.robots} == {"k" if r.policy == "kitchen" else "s"}, r
        assert len(r.robots) <= (2 if r.policy == "sorting" else 3)  # each policy's own cap
    assert server.loop.stats.batches_by_policy["sorting"] > 0 and server.loop.stats.batches_by_policy["kitchen"] > 0
    assert "batches=kitchen:" in server.status_line()
    metric = server.metrics.registry.get_sample_value
    for name in ("kitchen", "sorting"):
        assert metric("armory_policy_batches_total", {"policy": name}) == server.loop.stats.batches_by_policy[name]
        assert metric("armory_policy_device_seconds_total", {"policy": name}) > 0


def test_policies_file_problems_are_one_line_each(tmp_path):
    bad = [
        ({}, "expected a mapping"),
        ({"a b": {"path": "x"}}, "a name is"),
        ({"a": "x"}, "expected a mapping with path"),
        ({"a": {"path": ""}}, "path must be"),
        ({"a": {"path": "x", "max_batch_size": 0}}, "max_batch_size"),
        ({"a": {"path": "x", "colour": 1}}, "unknown key(s) colour"),
        ({"a": {"path": "x", "overrides": 3}}, "overrides must be"),
    ]
    for data, why in bad:
        with pytest.raises(ConfigError, match="policies") as err:
            policies_from_dict(data, "f.yaml")
        assert why in str(err.value), (data, err.value)
    ok = policies_from_dict({"pi": {"path": "lerobot/pi05_libero", "overrides": {"dtype": "bfloat16", "compile_model": True}}})
    assert ok[0].overrides == ("dtype=bfloat16", "compile_model=true") and ok[0].max_batch_size is None
    (tmp_path / "p.yaml").write_text("act:\n  path: /m/act\n  overrides: [n_action_steps=10]\n  max_batch_size: 4\n")
    (entry,) = load_policies(str(tmp_path / "p.yaml"))
    assert (entry.name, entry.path, entry.overrides, entry.max_batch_size) == ("act", "/m/act", ("n_action_steps=10",), 4)
    with pytest.raises(ConfigError, match="not both"):
        ServerConfig(policy=PolicyOptions("x"), policies="p.yaml").validate()


def test_a_swap_of_one_policy_leaves_the_other_serving(two_policy_server):
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

    server, _, records, root = two_policy_server
    make_demo_policy(DemoPolicyConfig(output=str(root / "sorting-v2"), **{**TINY, "state_dim": 3, "seed": 2}))
    kitchen_engine = server.loop.policies["kitchen"].engine
    info = server.metrics.registry.get_sample_value
    def served(policy: str, path: Path) -> float | None:
        return info("armory_policy_info", {"policy": policy, "path": str(path)})

    assert served("kitchen", root / "kitchen") == served("sorting", root / "sorting") == 1.0
    result = server.swappers["sorting"].swap(str(root / "sorting-v2"))
    assert result.result == "ok", result.message
    # Metrics show both policies' checkpoints: the swapped one's new path, the other's unchanged.
    assert served("sorting", root / "sorting-v2") == 1.0
    assert served("sorting", root / "sorting") is None
    assert served("kitchen", root / "kitchen") == 1.0
    from prometheus_client import generate_latest

    from lerobot_armory.entrypoints.status import render

    view = render(generate_latest(server.metrics.registry).decode())
    assert f"policies kitchen={root / 'kitchen'}, sorting={root / 'sorting-v2'}; swaps ok 1" in view
    assert server.loop.policies["sorting"].engine.path == str(root / "sorting-v2")
    # Loaded for its own cap (2), not the first policy's (3): its scheduler's table has 2 entries.
    assert len(server.loop.policies["sorting"].scheduler.d_infer) == 2
    assert server.loop.policies["kitchen"].engine is kitchen_engine and server.swappers["kitchen"].current.path == str(root / "kitchen")
    # New registrations for the swapped policy are told its new checkpoint.
    conn = Connection(server.address)
    try:
        assert "sorting-v2" in conn.register("s-new", SORTING, 10.0, 1, 5, policy_name="sorting").policy
    finally:
        conn.close()
    # A checkpoint whose features differ from the policy it replaces is refused.
    refused = server.swappers["sorting"].swap(str(root / "kitchen"))
    assert refused.result == "refused" and server.loop.policies["sorting"].engine.path == str(root / "sorting-v2")


def test_a_hostile_policy_name_is_refused_in_one_short_line_and_hurts_nobody(two_policy_server):
    server, _, _, _ = two_policy_server
    batches = server.loop.stats.batches
    conn = Connection(server.address)
    try:
        for name in ("x" * 100_000, "kitchen\n" * 50, "../../etc/passwd", "\x00"):
            with pytest.raises(grpc.RpcError) as err:
                conn.register("hostile", KITCHEN, 10.0, 1, 5, policy_name=name)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and len(err.value.details()) < 400
        ok = conn.register("after-hostile", KITCHEN, 10.0, 1, 5, policy_name="kitchen")
        assert ok.action_dim == 2 and server.loop.alive and server.loop.error is None
    finally:
        conn.close()
    assert server.loop.stats.batches >= batches


def test_openpi_clients_are_served_by_the_first_policy_by_its_name(two_policy_server):
    """openpi clients cannot name a policy: their sessions carry the first policy's name, not an
    implicit default, and their batches run on it."""
    from websockets.sync.client import connect

    from lerobot_armory.entrypoints.openpi.codec import pack, unpack
    from lerobot_armory.serving.config import OpenpiOptions

    server, _, records, _ = two_policy_server
    port = server.serve_openpi(OpenpiOptions(port=0))
    try:
        with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
            unpack(ws.recv(), 1 << 20)
            shapes = {f.name: f.shape for f in server.policy.wire_features}
            image = np.zeros(shapes["observation.images.front"], np.uint8)
            ws.send(pack({"observation/state": np.zeros(2, np.float32), "observation/image": image, "prompt": "x"}))
            raw = ws.recv(timeout=30)
            assert isinstance(raw, bytes), raw  # a str is the server's refusal
            reply = unpack(raw, 1 << 20)
            with server.fleet.cond:
                sessions = [s for s in server.fleet.active() if s.spec.robot_id.startswith("openpi")]
            assert [s.policy for s in sessions] == ["kitchen"]
            robot = sessions[0].spec.robot_id
        assert reply["actions"].shape[1] == server.loop.policies["kitchen"].engine.action_dim
        assert {r.policy for r in records if robot in r.robots} == {"kitchen"}
    finally:
        server.openpi.stop()
        server.openpi = None
