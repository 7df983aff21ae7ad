"""The echo engine: a test double that serves chunks without a model, and a server around it.

Each chunk's actions all equal its robot's first state value, so a robot can tell its own chunk
from another's. The load, transport and adversarial tests serve it, and ``benchmarks/load.py`` and
``benchmarks/adversarial.py`` borrow it.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np

from lerobot_armory.engine.protocol import UnguidedEngine
from lerobot_armory.robot.client import ArmoryClient, RobotIdentity
from lerobot_armory.entrypoints.grpc.service import PolicyInfo
from lerobot_armory.entrypoints.server import ArmoryServer
from lerobot_armory.feature_spec import FeatureSpec
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.schedulers import LookaheadConfig, SchedulerConfig

FEATURES = {"observation.state": ("float32", (4,))}


class EchoEngine(UnguidedEngine):
    """Chunks whose actions all equal the robot's first state value (a robot can tell its own
    chunk from another's); optionally slow."""

    def __init__(self, delay_s: float = 0.0) -> None:
        self.delay_s = delay_s

    def infer(self, observations, tasks, noise_seeds=None, history=None) -> np.ndarray:
        if self.delay_s:
            time.sleep(self.delay_s)
        first = np.array([o["observation.state"][0] for o in observations], np.float32)
        return np.repeat(first[:, None, None], 10, axis=1).repeat(2, axis=2)


def echo_server(engine: Any = None, cap: int = 4, scheduler: SchedulerConfig | None = None, **kwargs: Any) -> ArmoryServer:
    """A started server on a free loopback port with the echo engine and state-only robots."""
    info = PolicyInfo("echo", [FeatureSpec("observation.state", "float32", (4,))], ["a", "b"], 10)
    profile = LatencyProfile("echo", tuple(5.0 + k for k in range(cap)))
    return ArmoryServer(engine or EchoEngine(), info, profile, scheduler or LookaheadConfig(), cap, port=0, **kwargs).start()


def echo_robots(server: ArmoryServer, n: int, seconds: float) -> list[ArmoryClient]:
    """``n`` state-only robots (``r0``...; robot k sends state k) run against ``server`` for
    ``seconds``, each on its own thread; returns the clients once all have stopped and been
    closed (a client left open would keep reconnecting, and logging, after its server stops)."""
    clients = []
    for k in range(n):
        state = np.full(4, float(k), np.float32)
        clients.append(
            ArmoryClient(
                server.address, RobotIdentity(f"r{k}", 20.0, 2, 10), FEATURES,
                observe=lambda state=state: {"observation.state": state}, act=lambda a: None,
            )  # fmt: skip
        )
    threads = [threading.Thread(target=c.run, args=(seconds,)) for c in clients]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for c in clients:
        c.close()
    return clients
