"""Robot side: the action buffer, the client loop with armory_sim robots against a real server,
starvation under a slow server, reconnects without stale chunks, refused registrations, clock-sync
answers, a full server waited for, grant-rule grants."""

from __future__ import annotations

import itertools
import logging
import socket
import threading
import time

import numpy as np
import pytest

from tests.support.echo import FEATURES as ECHO_FEATURES
from tests.support.echo import echo_server
from tests.support.pusher import wait_for
from lerobot_armory.network_delay import LogNormalDelay
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.robot.actions import ActionBuffer
from lerobot_armory.robot.armory_sim import ArmorySim, ArmorySimConfig
from lerobot_armory.robot.client import ArmoryClient, Backoff, RegistrationRefused, RobotIdentity
from lerobot_armory.robot.connection import Connection, Registration
from lerobot_armory.robot.features import FeatureMap
from lerobot_armory.robot.netem import NetworkEmulator
from lerobot_armory.schedulers import EarliestDeadlineConfig
from lerobot_armory.entrypoints.server import ArmoryServer
from lerobot_armory.entrypoints.grpc.service import PolicyInfo
from lerobot_armory.wire import FeatureSpec
from lerobot_armory.engine.protocol import UnguidedEngine

SIM_FEATURES = [FeatureSpec("observation.state", "float32", (2,)), FeatureSpec("observation.images.front", "uint8", (32, 32, 3))]


# ---- action buffer ---------------------------------------------------------------------------


def test_buffer_uses_newest_covering_chunk_and_never_beyond_h_max():
    buf = ActionBuffer(h_max=3)
    buf.add(0, 0, np.arange(10.0)[:, None], arrival_time=0.0)
    assert buf.action_for(0)[0] == 0.0
    buf.add(1, 1, 100 + np.arange(10.0)[:, None], arrival_time=0.1)
    assert buf.action_for(1)[0] == 100.0  # newest chunk wins
    assert buf.action_for(2)[0] == 101.0
    assert buf.action_for(3)[0] == 102.0
    assert buf.action_for(4) is None  # chunk 1 covers [1, 4) only (h_max = 3), chunk 0 [0, 3)
    receipts = buf.take_receipts()
    assert (0, 0.0, 0) in receipts and (1, 0.1, 0) in receipts
    assert dict(buf.first_executed_index) == {"0": 2}


def test_buffer_reports_late_chunks_as_unused_and_clear_drops_everything():
    buf = ActionBuffer(h_max=2)
    buf.add(0, 0, np.zeros((5, 1)), 0.0)
    buf.action_for(0)
    buf.action_for(1)
    buf.add(1, 0, np.ones((5, 1)), 0.2)  # arrives after the robot passed index 1
    assert buf.action_for(2) is None
    assert (1, 0.2, -1) in buf.take_receipts()
    buf.add(2, 2, np.ones((5, 1)), 0.3)
    buf.clear()
    assert buf.action_for(2) is None


def test_buffer_measures_the_seam_at_every_switch_to_a_newer_chunk():
    def chunk(i_start: int, y: float, dx: float = 0.0, n: int = 10) -> np.ndarray:
        """Actions a(i) = (i + dx, y) for the absolute indices i_start .. i_start + n - 1."""
        return np.stack([np.arange(i_start, i_start + n) + dx, np.full(n, y)], axis=1)

    buf = ActionBuffer(h_max=4)
    buf.add(0, 0, chunk(0, 0.0), 0.0)
    buf.action_for(0)
    buf.action_for(1)
    assert buf.seam_stats()["seams"] == 0  # the first chunk is no seam
    buf.add(1, 1, chunk(1, 4.0), 0.1)  # disagrees with the old chunk by (0, 4) at every index
    assert buf.action_for(2)[1] == 4.0  # switch at index 2: jump 4
    buf.action_for(3)
    buf.add(2, 2, chunk(2, 0.0, dx=3.0), 0.2)  # switch at index 4: (4, 4) -> (7, 0), jump 5
    buf.action_for(4)
    stats = buf.seam_stats()
    assert stats["seams"] == 2 and stats["seam_jump_mean"] == pytest.approx(4.5)
    assert 4.0 < stats["seam_jump_p95"] <= 5.0
    buf.add(3, 5, chunk(5, 0.0, n=1), 0.3)  # a one-action chunk: holds index 5 only
    buf.action_for(5)
    assert buf.seam_stats()["seams"] == 3  # chunk 2 -> 3 at index 5: (8, 0) -> (5, 0), jump 3
    # Each seam is logged with its new chunk's start and the offset switched at (for RTC's study).
    assert buf.seam_stats()["seam_log"] == [[1, 1, 4.0], [2, 2, 5.0], [5, 0, 3.0]]
    assert buf.action_for(6) is None  # chunk 2 covers [2, 6), chunk 3 [5, 6): the robot starves
    buf.add(4, 6, chunk(6, 0.0), 0.5)
    buf.action_for(6)  # chunk 3 holds no action for index 6: a switch after a gap, no seam value
    assert buf.seam_stats()["switches_after_gap"] == 1 and buf.seam_stats()["seams"] == 3
    buf.clear()
    buf.add(5, 20, chunk(20, 9.0), 1.0)
    buf.action_for(20)
    assert buf.seam_stats()["seams"] == 3  # a new session's first chunk is no seam


def test_feature_map_follows_lerobot_conventions():
    fmap = FeatureMap.for_robot({"x.pos": float, "y.pos": float, "front": (32, 32, 3)}, {"x.pos": float, "y.pos": float})
    assert fmap.wire_features() == {"observation.state": ("float32", (2,)), "observation.images.front": ("uint8", (32, 32, 3))}
    wire = fmap.to_wire({"x.pos": 0.5, "y.pos": -0.5, "front": np.zeros((32, 32, 3), np.uint8)})
    np.testing.assert_array_equal(wire["observation.state"], np.array([0.5, -0.5], np.float32))
    assert fmap.to_action(np.array([0.1, 0.2])) == {"x.pos": pytest.approx(0.1), "y.pos": pytest.approx(0.2)}
    with pytest.raises(ValueError, match="dims"):
        fmap.to_action(np.zeros(3))


# ---- against a real server -------------------------------------------------------------------


class ConstEngine(UnguidedEngine):
    """Returns chunks whose every action equals ``value`` (optionally slow)."""

    def __init__(self, value: float, delay_s: float = 0.0, horizon: int = 10) -> None:
        self.value, self.delay_s, self.horizon = value, delay_s, horizon

    def infer(self, observations, tasks, noise_seeds=None, history=None):
        if self.delay_s:
            time.sleep(self.delay_s)
        return np.full((len(observations), self.horizon, 2), self.value, np.float32)


def start_server(engine, port: int = 0, cap: int = 3, **kwargs) -> ArmoryServer:
    info = PolicyInfo("test engine", SIM_FEATURES, ["x", "y"], 10)
    profile = LatencyProfile("t", (5.0, 6.0, 7.0))
    return ArmoryServer(engine, info, profile, EarliestDeadlineConfig(), cap, port=port, **kwargs).start()


def sim_client(address: str, name: str, scene: str = "static", tier: str = "slow", h_max: int = 8, fps: float = 20.0, backoff=None):
    robot = ArmorySim(ArmorySimConfig(scene=scene, image_size=32))
    robot.connect()
    fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
    executed = []

    def act(vector):
        executed.append((time.monotonic(), client.index, vector.copy()))
        robot.send_action(fmap.to_action(vector))

    client = ArmoryClient(
        address,
        RobotIdentity(name, fps=fps, h_min=2, h_max=h_max, tier=tier),
        fmap.wire_features(),
        observe=lambda: fmap.to_wire(robot.get_observation()),
        act=act,
        backoff=backoff,
    )
    return client, robot, executed


def run_in_thread(client: ArmoryClient, duration_s: float):
    out = {}
    t = threading.Thread(target=lambda: out.update(client.run(duration_s)), daemon=True)
    t.start()
    return t, out


@pytest.mark.slow
def test_fleet_of_sim_robots_executes_chunks_in_order(engine):
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    server = ArmoryServer(engine, info, LatencyProfile("t", (15.0, 20.0, 25.0)), EarliestDeadlineConfig(), 3, port=0).start()
    received: dict[str, list] = {}
    runs = []
    try:
        for k, (scene, tier) in enumerate([("dynamic", "fast"), ("dynamic", "fast"), ("static", "slow")]):
            client, robot, executed = sim_client(server.address, f"sim{k}", scene, tier, h_max=8 if tier == "fast" else 10)
            chunks = received.setdefault(client.identity.robot_id, [])
            original = client.buffer.add

            def spy(chunk_id, i_start, actions, arrival, original=original, chunks=chunks):
                chunks.append((chunk_id, i_start, actions, arrival))
                original(chunk_id, i_start, actions, arrival)

            client.buffer.add = spy
            runs.append((client, robot, executed, *run_in_thread(client, 3.0)))
        for client, robot, executed, thread, out in runs:
            thread.join(20)
            stats = out
            client.close()
            assert stats["executed_steps"] + stats["starved_steps"] == stats["ticks"] > 30
            assert stats["executed_steps"] > 20
            chunks = received[client.identity.robot_id]
            indices = [i for _, i, _ in executed]
            assert indices == list(range(len(indices))), "indices must increase by one per executed step"
            for t, i, vector in executed:
                # the action executed at index i is action (i - i_start) of the newest chunk that
                # had arrived and covers i within h_max
                cands = [c for c in chunks if c[3] <= t and c[1] <= i < c[1] + client.identity.h_max]
                assert cands, f"index {i} executed with no covering chunk"
                newest = max(cands, key=lambda c: (c[1], c[0]))
                np.testing.assert_allclose(vector, newest[2][i - newest[1]])
    finally:
        server.stop(grace_s=0.5)


@pytest.mark.slow
def test_starvation_is_counted_when_the_server_is_slow():
    fast_server = start_server(ConstEngine(0.0))
    client, _, _ = sim_client(fast_server.address, "quick", h_max=8)
    quick = client.run(2.0)
    client.close()
    fast_server.stop(0.5)

    slow_server = start_server(ConstEngine(0.0, delay_s=0.5))
    client, _, _ = sim_client(slow_server.address, "starving", h_max=4)
    slow = client.run(3.0)
    client.close()
    slow_server.stop(0.5)
    assert quick["starvation_pct"] < 20
    assert slow["starvation_pct"] > 40, slow
    assert slow["executed_steps"] + slow["starved_steps"] == slow["ticks"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_reconnect_never_replays_a_stale_chunk():
    port = free_port()
    first = start_server(ConstEngine(+1.0, horizon=10), port=port)
    client, _, executed = sim_client(f"127.0.0.1:{port}", "phoenix", h_max=10, backoff=Backoff(0.2, 0.5))
    thread, out = run_in_thread(client, 6.0)
    assert wait_for(lambda: any(v[0] == 1.0 for _, _, v in executed), timeout=10)
    first.stop(grace_s=0.2)
    assert wait_for(lambda: bool(client.losses), timeout=10)
    starved = client.starved
    assert wait_for(lambda: client.starved >= starved + 20, timeout=10)  # it holds with no server
    # From the moment the robot notices the loss (its stream closes: on a loaded machine that can
    # come after stop() returns) it holds; one control tick of slack for an action already taken
    # from the buffer when the close landed.
    assert client.losses, "the robot did not notice the server stop"
    t_lost = client.losses[0][0] + 1.0 / 20.0
    index_while_down = client.index
    second = start_server(ConstEngine(-1.0, horizon=10), port=port)
    try:
        thread.join(20)
    finally:
        client.close()
        second.stop(0.5)
    stats = out
    assert stats["reconnects"] >= 1
    after = [(t, i, v) for t, i, v in executed if t > t_lost]
    assert after, "the robot never resumed after the reconnect"
    assert all(v[0] == -1.0 for _, _, v in after), "a chunk from before the reconnect was executed"
    assert min(i for _, i, _ in after) >= index_while_down
    assert stats["starved_steps"] >= 15  # it held while the server was gone


def test_registration_errors_surface_with_the_servers_reason():
    server = start_server(ConstEngine(0.0))
    try:
        client, _, _ = sim_client(server.address, "bad", h_max=99)
        with pytest.raises(RegistrationRefused, match="h_max"):
            client.connect()
    finally:
        server.stop(0.5)


def test_unreachable_server_is_retried_then_given_up():
    client, _, _ = sim_client(f"127.0.0.1:{free_port()}", "lonely", backoff=Backoff(0.1, 0.2, give_up_s=1.0))
    start = time.monotonic()
    with pytest.raises(ConnectionError, match="unreachable"):
        client.connect()
    assert 0.5 < time.monotonic() - start < 10


@pytest.mark.slow
def test_client_waits_for_a_server_that_comes_up_late():
    port = free_port()
    client, _, _ = sim_client(f"127.0.0.1:{port}", "patient", backoff=Backoff(0.1, 0.3))
    holder = {}
    t = threading.Thread(target=lambda: holder.update(stats=client.run(2.0)), daemon=True)
    t.start()
    time.sleep(1.0)  # what is tested: the server comes up a second after the robot started asking
    server = start_server(ConstEngine(0.0), port=port)
    try:
        t.join(20)
    finally:
        client.close()
        server.stop(0.5)
    assert holder["stats"]["executed_steps"] > 0


def test_client_command_exits_1_with_the_reason_and_2_on_bad_flags(capsys):
    from lerobot_armory.robot.cli import main

    server = start_server(ConstEngine(0.0))
    try:
        with pytest.raises(SystemExit) as info:
            main(["--robot.type=armory_sim", "--robot.image_size=32", f"--server_address={server.address}", "--h_max=50", "--h_min=1"])
        assert info.value.code == 1
        assert "h_max" in capsys.readouterr().err
    finally:
        server.stop(0.5)
    with pytest.raises(SystemExit) as info:
        main(["--robot.type=armory_sim", "--fps=0"])
    assert info.value.code == 2
    assert "fps" in capsys.readouterr().err


def test_client_command_runs_and_writes_stats(tmp_path, capsys):
    import json

    from lerobot_armory.robot.cli import main

    server = start_server(ConstEngine(0.2))
    try:
        stats_path = tmp_path / "stats.json"
        main(
            [
                "--robot.type=armory_sim", "--robot.image_size=32", "--robot.scene=dynamic", f"--server_address={server.address}",
                "--fps=20", "--h_min=2", "--h_max=8", "--tier=fast", "--duration_s=1.5", f"--stats_path={stats_path}",
            ]
        )  # fmt: skip
    finally:
        server.stop(0.5)
    stats = json.loads(stats_path.read_text())
    for key in ("robot_id", "ticks", "executed_steps", "starved_steps", "starvation_pct", "chunks_received", "first_executed_index", "successes"):
        assert key in stats
    assert stats["executed_steps"] > 0 and stats["chunks_received"] > 0
    assert "successes" in capsys.readouterr().out


# ---- clock sync requests ---------------------------------------------------------------------


class FakeStreamCall:
    """Stands for the gRPC stream call: yields the given server messages (noting when), then ends."""

    def __init__(self, messages: list[pb.ServerMessage], clock) -> None:
        self.messages, self.clock, self.yielded_at = messages, clock, []

    def __iter__(self):
        for msg in self.messages:
            self.yielded_at.append(self.clock())
            yield msg

    def cancel(self) -> None:
        pass


def fake_stream_connection(messages: list[pb.ServerMessage], clock, network=None) -> tuple[Connection, FakeStreamCall]:
    """A Connection whose stream is ``messages`` (no server: the channel is never used)."""
    conn = Connection("127.0.0.1:1", clock=clock, network=network)
    call = FakeStreamCall(messages, clock)
    conn.stub = type("FakeStub", (), {"Stream": lambda self, requests, metadata=None: call})()
    first_sync = pb.ClockSync(client_send_time=1.0, client_recv_time=2.0)
    conn.registration = Registration("session", ["x", "y"], 10, "fake", [], first_sync)
    return conn, call


def sync_request(sync_id: int, server_send_time: float) -> pb.ServerMessage:
    return pb.ServerMessage(sync_request=pb.ClockSyncRequest(sync_id=sync_id, server_send_time=server_send_time))


def test_sync_request_is_answered_at_once_with_robot_clock_stamps():
    ticks = itertools.count(100.0, 0.5)  # a robot clock nowhere near the server's, advancing on every read
    conn, _ = fake_stream_connection([sync_request(7, 5000.0)], clock=lambda: next(ticks))
    try:
        conn.open_stream(on_chunk=lambda chunk: None)
        assert conn.closed.wait(5)
        first, answer = conn._outgoing.get(timeout=1), conn._outgoing.get(timeout=1)
        assert first.clock_sync.sync_id == 0  # the registration round trip goes first, as before
        sync = answer.clock_sync
        assert answer.WhichOneof("kind") == "clock_sync" and sync.sync_id == 7
        assert sync.server_send_time == 5000.0  # echoed
        assert 100.0 <= sync.client_recv_time < sync.client_send_time < 1000.0  # robot clock, received before sent
        assert conn._outgoing.empty()
    finally:
        conn.close()


def test_sync_answer_is_stamped_after_the_emulated_downlink_and_uplink():
    down, up = 0.08, 0.05
    network = NetworkEmulator(uplink=LogNormalDelay(up, 0.0), downlink=LogNormalDelay(down, 0.0))
    conn, call = fake_stream_connection([sync_request(3, 1.0)], clock=time.monotonic, network=network)
    try:
        conn.open_stream(on_chunk=lambda chunk: None)
        conn._outgoing.get(timeout=1)  # the registration sync, queued directly
        sync = conn._outgoing.get(timeout=2).clock_sync
        assert sync.sync_id == 3
        assert sync.client_recv_time - call.yielded_at[0] >= down  # seen when a chunk would be
        assert sync.client_send_time - sync.client_recv_time >= up  # stamped when it enters the stream
    finally:
        conn.close()


# ---- a full server ---------------------------------------------------------------------------


def light_client(address: str, name: str, backoff: Backoff) -> ArmoryClient:
    state = np.zeros(4, np.float32)
    identity = RobotIdentity(name, fps=20.0, h_min=2, h_max=8)
    observe = lambda: {"observation.state": state}
    return ArmoryClient(address, identity, ECHO_FEATURES, observe=observe, act=lambda a: None, backoff=backoff)


def test_a_full_server_is_waited_for_then_joined(caplog):
    caplog.set_level(logging.WARNING, logger="lerobot_armory.robot.client")
    server = echo_server(max_robots=1)
    first = light_client(server.address, "squatter", Backoff(0.1, 0.3))
    second = light_client(server.address, "waiting", Backoff(0.1, 0.3))
    try:
        first_thread, _ = run_in_thread(first, 0.0)  # runs until closed: holds the only slot
        deadline = time.monotonic() + 5
        while not first.connected and time.monotonic() < deadline:
            time.sleep(0.05)
        assert first.connected

        impatient = light_client(server.address, "impatient", Backoff(0.1, 0.2, give_up_s=1.0))
        with pytest.raises(ConnectionError, match="RESOURCE_EXHAUSTED.*gave up"):
            impatient.connect()  # retried (not refused) until give_up_s

        outcome: dict[str, BaseException | None] = {}

        def connect() -> None:
            try:
                second.connect()
                outcome["error"] = None
            except BaseException as exc:  # noqa: BLE001 - the test reports whatever it was
                outcome["error"] = exc

        waiting = threading.Thread(target=connect, daemon=True)
        waiting.start()
        time.sleep(1.5)  # what is tested: 1.5 s later it still waits (neither refused nor connected)
        assert waiting.is_alive() and not outcome, f"a full server must be waited for, got {outcome}"
        assert not second.connected
        reasons = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert any("RESOURCE_EXHAUSTED" in m and "max_robots" in m and "retrying" in m for m in reasons), reasons

        first.close()
        first_thread.join(5)
        waiting.join(5)
        assert outcome == {"error": None}, outcome
        assert second.connected
    finally:
        first.close()
        second.close()
        server.stop(0.5)


def test_client_command_waits_for_a_full_server_until_give_up(capsys):
    from lerobot_armory.robot.cli import main

    server = start_server(ConstEngine(0.0), max_robots=1)
    squatter, _, _ = sim_client(server.address, "squatter")
    try:
        squatter.connect()
        start = time.monotonic()
        with pytest.raises(SystemExit) as info:
            main(
                [
                    "--robot.type=armory_sim", "--robot.image_size=32", f"--server_address={server.address}",
                    "--h_min=1", "--h_max=8", "--give_up_s=1.0", "--backoff.initial_s=0.1", "--backoff.max_s=0.2",
                ]
            )  # fmt: skip
        assert info.value.code == 1
        assert time.monotonic() - start >= 0.8  # it retried rather than exiting at the first refusal
        last = capsys.readouterr().err.strip().splitlines()[-1]
        assert "RESOURCE_EXHAUSTED" in last and "gave up" in last, last
    finally:
        squatter.close()
        server.stop(0.5)


# ---- grant-rule grants ---------------------------------------------------------------------


def test_registration_reads_the_grant_or_none():
    response = pb.RegisterResponse(session_id="s", action_names=["x", "y"], chunk_size=10, policy="p")
    assert Registration.from_response(response, pb.ClockSync()).granted is None  # a server without grant rules
    grant = pb.Grant(weight=0.5, tier="fast", fps=30.0, h_min=2, h_max=6, max_device_share=0.25, rule="robot:a")
    response.granted.CopyFrom(grant)
    reg = Registration.from_response(response, pb.ClockSync(sync_id=0, client_recv_time=3.0))
    assert reg.granted == grant
    assert (reg.session_id, reg.action_dim, reg.clock_sync.client_recv_time) == ("s", 2, 3.0)


@pytest.fixture
def grant_injected(monkeypatch):
    """Makes every registration carry ``holder["grant"]``, whatever the server sends (it may not send one yet)."""
    holder: dict[str, pb.Grant] = {}
    original = Connection.register

    def register(self, *args, **kwargs):
        reg = original(self, *args, **kwargs)
        reg.granted = holder["grant"]
        return reg

    monkeypatch.setattr(Connection, "register", register)
    return holder


def test_grant_is_logged_and_a_smaller_h_max_is_used(grant_injected, caplog):
    caplog.set_level(logging.INFO, logger="lerobot_armory.robot.client")
    grant_injected["grant"] = pb.Grant(weight=0.5, tier="slow", fps=20.0, h_min=2, h_max=5, rule="robot:capped")
    server = start_server(ConstEngine(0.0))
    client, _, _ = sim_client(server.address, "capped", h_max=8, fps=20.0)
    try:
        client.connect()
        assert client.buffer.h_max == 5  # the server plans chunks for the granted horizon
        assert client.granted is not None and client.granted.rule == "robot:capped"
        infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert any("granted" in m and "robot:capped" in m and "h_max 5" in m for m in infos), infos
        assert len(warnings) == 1, warnings
        assert "weight asked 1 granted 0.5" in warnings[0] and "h_max asked 8 granted 5" in warnings[0]
        assert "tier" not in warnings[0] and "h_min" not in warnings[0]  # only what changed
    finally:
        client.close()
        server.stop(0.5)


def test_grant_at_another_fps_is_refused_and_the_session_given_back(grant_injected):
    grant_injected["grant"] = pb.Grant(weight=1.0, tier="slow", fps=10.0, h_min=2, h_max=8, rule="default")
    server = start_server(ConstEngine(0.0))
    client, _, _ = sim_client(server.address, "too-fast", fps=20.0)
    try:
        with pytest.raises(RegistrationRefused, match="granted fps 10 but this robot runs at fps 20"):
            client.connect()
        assert not client.connected
        deadline = time.monotonic() + 3
        while server.fleet.sessions and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not server.fleet.sessions  # given back at once, not left to expire
    finally:
        client.close()
        server.stop(0.5)


def test_armory_sim_reports_the_jerk_of_its_commanded_actions():
    robot = ArmorySim(ArmorySimConfig(scene="static", image_size=32))
    robot.connect()
    assert robot.task_stats()["action_jerk_mean"] is None  # fewer than four actions
    # A straight line at constant speed has no jerk; then one jump of 0.5 in x.
    for x in (0.0, 0.1, 0.2, 0.3, 0.4):
        robot.send_action({"x.pos": x, "y.pos": 0.0})
    assert robot.task_stats()["action_jerk_max"] == pytest.approx(0.0, abs=1e-12)
    robot.send_action({"x.pos": 1.0, "y.pos": 0.0})  # expected 0.5: third difference 0.5
    stats = robot.task_stats()
    assert stats["action_jerk_max"] == pytest.approx(0.5)
    assert stats["action_jerk_mean"] == pytest.approx(0.5 / 3)


# ---- episodes ----------------------------------------------------------------------------------


def test_buffer_drop_chunks_keeps_their_receipts_and_an_unused_arrival_is_reported():
    buf = ActionBuffer(h_max=5)
    buf.add(0, 0, np.zeros((5, 1)), 0.0)
    buf.action_for(0)
    buf.add(1, 1, np.ones((5, 1)), 0.1)
    buf.drop_chunks()
    assert buf.action_for(1) is None and buf.current is None
    buf.add_unused(2, 0.3)
    receipts = buf.take_receipts()
    assert (0, 0.0, 0) in receipts and (1, 0.1, -1) in receipts and (2, 0.3, -1) in receipts


class EpisodeEchoEngine(UnguidedEngine):
    """Chunks whose every action is the observation's first state value (the robot's episode)."""

    def __init__(self, delay_s: float = 0.0) -> None:
        self.delay_s = delay_s

    def infer(self, observations, tasks, noise_seeds=None, history=None):
        if self.delay_s:
            time.sleep(self.delay_s)
        values = np.array([obs["observation.state"][0] for obs in observations], np.float32)
        return np.repeat(values[:, None, None], 10, axis=1).repeat(2, axis=2)


@pytest.mark.slow
@pytest.mark.parametrize(("delay_s", "h_min"), [(0.0, 8), (0.12, 2)])
def test_after_an_episode_boundary_no_old_chunk_runs_and_a_fresh_one_comes_at_once(delay_s, h_min):
    """A robot that resets its world every 0.5 s: every action it executes carries the episode
    it was executed in (none of the old world's), and each new episode is served without waiting
    for h_min executed actions. With a slow engine and h_min = 2 a chunk is nearly always in
    flight, so some arrive after a reset, tagged with their old episode, and are dropped."""
    features = [FeatureSpec("observation.state", "float32", (2,))]
    info = PolicyInfo("episode echo", features, ["x", "y"], 10)
    server = ArmoryServer(EpisodeEchoEngine(delay_s), info, LatencyProfile("t", (5.0, 6.0)), EarliestDeadlineConfig(), 2, port=0).start()
    fps = 20.0
    world = {"episode": 0, "start": time.monotonic()}
    executed: list[tuple[int, float]] = []

    def observe():
        if time.monotonic() - world["start"] > 0.5:  # the world resets (a success or a time limit)
            world["episode"] += 1
            world["start"] = time.monotonic()
        return {"observation.state": np.array([world["episode"], 0.0], np.float32)}

    client = ArmoryClient(
        server.address,
        RobotIdentity("resetter", fps=fps, h_min=h_min, h_max=10),
        {"observation.state": ("float32", (2,))},
        observe=observe,
        act=lambda vector: executed.append((world["episode"], float(vector[0]))),
        episode_of=lambda: world["episode"],
    )
    try:
        stats = client.run(4.0)
    finally:
        client.close()
        server.stop(grace_s=0.5)
    assert stats["episodes"] >= 6
    assert executed and all(episode == value for episode, value in executed), "an old episode's action ran"
    # Each episode lasts 10 ticks; one inference and one tick of delay later it acts again, so a
    # robot made to wait for h_min = 8 executed actions (which it never gets) would starve on.
    by_episode = {e: sum(1 for ep, _ in executed if ep == e) for e in range(1, stats["episodes"] - 1)}
    assert all(n >= 3 for n in by_episode.values()), by_episode
    if delay_s:
        assert stats["stale_episode_chunks"] >= 1
