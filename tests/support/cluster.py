"""Shared by the cluster tests: replica options, armory_sim robots on threads, and the stale-action check."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np

from lerobot_armory.robot.armory_sim import ArmorySim, ArmorySimConfig
from lerobot_armory.robot.client import ArmoryClient, Backoff, RobotIdentity
from lerobot_armory.robot.connection import Connection
from lerobot_armory.robot.features import FeatureMap
from lerobot_armory.schedulers import EarliestDeadlineConfig
from lerobot_armory.entrypoints.server import ServerConfig
from lerobot_armory.engine.options import EngineOptions
from lerobot_armory.engine.options import PolicyOptions
from tests.support.pusher import wait_for  # noqa: F401 - the one wait_for, re-exported for the cluster tests

IMAGE = 32


def make_planner(out) -> str:
    """The analytic armory_planner (deterministic, cheap) saved as a LeRobot policy dir."""
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

    make_demo_policy(DemoPolicyConfig(output=str(out), kind="planner", chunk_size=10, image_size=IMAGE))
    return str(out)


def replica_config(policy_dir: str) -> ServerConfig:
    """A replica: the planner on the CPU, batches taking an H100's π0.5 latency, EDF, b = 3."""
    return ServerConfig(
        policy=PolicyOptions(policy_dir, "cpu"),
        engine=EngineOptions(emulate_profile="h100-pi05"),
        scheduler=EarliestDeadlineConfig(),
        max_batch_size=3,
        status_interval_s=0.0,
        log_level="warning",
        port=0,
    )


@dataclass
class SimRobot:
    """One armory_sim robot running the real client loop on a thread."""

    client: ArmoryClient
    robot: ArmorySim
    thread: threading.Thread | None = None
    error: list[BaseException] = field(default_factory=list)

    def start(self, duration_s: float) -> None:
        def run() -> None:
            try:
                self.client.run(duration_s)
            except BaseException as exc:  # noqa: BLE001 - surfaced by the test
                self.error.append(exc)

        self.robot.connect()
        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()

    def join(self) -> dict:
        assert self.thread is not None
        self.thread.join(timeout=60)
        self.client.close()
        self.robot.disconnect()
        assert not self.error, self.error
        return self.client.stats()


def sim_robot(address: str, robot_id: str, fast: bool, seed: int, image_size: int = IMAGE) -> SimRobot:
    scene = "dynamic" if fast else "static"
    robot = ArmorySim(ArmorySimConfig(scene=scene, image_size=image_size, seed=seed))
    fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
    client = ArmoryClient(
        address,
        RobotIdentity(robot_id, 20.0, 1, 6 if fast else 10, 1.0, "fast" if fast else "slow", scene),
        fmap.wire_features(),
        observe=lambda: fmap.to_wire(robot.get_observation()),
        act=lambda vector: robot.send_action(fmap.to_action(vector)),
        backoff=Backoff(0.1, 0.5, give_up_s=30.0),
        record_actions=True,
    )
    return SimRobot(client, robot)


def stale_actions(client: ArmoryClient) -> list[tuple]:
    """Actions executed after a lost connection from a chunk of the lost session (or an older one)."""
    log = client.executed_log or []
    return [e for lost_t, lost_epoch in client.losses for e in log if e[0] >= lost_t and e[1] <= lost_epoch]



def start_fleet(address: str, n: int = 6, duration_s: float = 8.0):
    robots = [sim_robot(address, f"robot{k}", fast=k % 2 == 0, seed=k) for k in range(n)]
    for r in robots:
        r.start(duration_s)
        time.sleep(0.05)  # robots join one after another, as placement sees them
    return robots


def one_chunk(address: str) -> tuple[np.ndarray, str]:
    """Register robot "same" at ``address``, send one fixed observation; (its chunk, the stream address answered)."""
    conn = Connection(address)
    assert conn.wait_ready(5)
    robot = ArmorySim(ArmorySimConfig(scene="dynamic", image_size=IMAGE, seed=7))
    fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
    reg = conn.register("same", fmap.wire_features(), 20.0, 1, 6, tier="fast")
    got: list = []
    conn.open_stream(got.append)
    rng = np.random.default_rng(0)
    obs = {
        name: rng.integers(0, 255, size=shape, dtype=np.uint8) if dtype == "uint8" else rng.normal(size=shape).astype(dtype)
        for name, (dtype, shape) in fmap.wire_features().items()
    }
    conn.send_observation(0, obs, capture_time=time.monotonic())
    assert wait_for(lambda: bool(got), timeout=5.0)
    conn.close()
    return got[0].actions, reg.stream_address


class FreezableProxy:
    """A TCP proxy to ``127.0.0.1:target_port`` that can go silent: ``freeze()`` stops forwarding
    in both directions but keeps every connection open (a host that vanished without a reset)."""

    def __init__(self, target_port: int) -> None:
        import socket

        self._socket = socket
        self.target_port = target_port
        self.frozen = threading.Event()
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(64)
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            upstream = self._socket.create_connection(("127.0.0.1", self.target_port))
            for src, dst in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(src, dst), daemon=True).start()

    def _pump(self, src, dst) -> None:
        try:
            while True:
                data = src.recv(65536)
                if not data:
                    break
                while self.frozen.is_set():
                    time.sleep(0.05)  # hold everything: nothing is forwarded, nothing is closed
                dst.sendall(data)
        except OSError:
            pass

    def freeze(self) -> None:
        self.frozen.set()


class Refused(Exception):
    """A registration the front refused: ``"CODE: details"``."""


class RobotAt:
    """What the front's ``Register`` reads of a gRPC context, for a robot at ``host``: robots on many
    hosts without as many network interfaces (the front's forwarding to the replicas is real gRPC)."""

    def __init__(self, host: str) -> None:
        self._peer = f"ipv4:{host}:40000"

    def peer(self) -> str:
        return self._peer

    def time_remaining(self) -> float:
        return 5.0

    def invocation_metadata(self) -> tuple:
        return ()

    def abort(self, code, details: str) -> None:
        raise Refused(f"{code.name}: {details}")


def register_from(front, host: str, request) -> str:
    """Register ``request`` with ``front`` (a ClusterFront) through its gRPC servicer, as a robot
    at ``host`` would: "OK" or "CODE: details"."""
    from lerobot_armory.entrypoints.cluster.front_service import FrontService

    try:
        FrontService(front).Register(request, RobotAt(host))
        return "OK"
    except Refused as exc:
        return str(exc)
