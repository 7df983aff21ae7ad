"""``lerobot-armory-cluster`` end to end on a Ray cluster started with ``ray start --head``.

The front (the CLI process) is stopped with SIGTERM while a robot runs, and started again: the
replicas are detached, named actors, so they keep serving the robot, which never reconnects, and
the new front finds them by name and sees the robot.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("ray")
# ``ray start --head`` and the cluster command: one worker of pytest-xdist runs the Ray tests.
pytestmark = [pytest.mark.ray, pytest.mark.slow, pytest.mark.subprocess, pytest.mark.xdist_group("ray")]

from tests.support.cluster import make_planner, sim_robot, wait_for  # noqa: E402

BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def ray_head(tmp_path):
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    port = free_port()
    started = subprocess.run(
        [str(BIN / "ray"), "start", "--head", f"--port={port}", "--num-cpus=4", "--include-dashboard=false",
         "--disable-usage-stats"],
        capture_output=True, text=True, timeout=180, env=env, check=False,
    )  # fmt: skip
    assert started.returncode == 0, started.stderr[-2000:]
    yield env
    subprocess.run([str(BIN / "ray"), "stop", "--force"], capture_output=True, timeout=120, env=env, check=False)


def start_front(planner: str, port: int, log: Path, env: dict) -> subprocess.Popen:
    args = [
        str(BIN / "lerobot-armory-cluster"), "--ray.address=auto", "--ray.namespace=armory-cli-test", f"--policy.path={planner}",
        "--policy.device=cpu", "--replicas=2", "--replica.num_gpus=0", "--engine.emulate_profile=h100-pi05", f"--port={port}",
        "--status_interval_s=0", "--log_level=info",
    ]  # fmt: skip
    return subprocess.Popen(args, stdout=log.open("w"), stderr=subprocess.STDOUT, env=env)


def test_the_front_restarts_and_no_running_robot_notices(ray_head, tmp_path):
    planner = make_planner(tmp_path / "planner")
    port = free_port()
    first = start_front(planner, port, tmp_path / "front1.log", ray_head)
    second = None
    try:
        assert wait_for(lambda: "front listening" in (tmp_path / "front1.log").read_text(), timeout=180)
        robot = sim_robot(f"127.0.0.1:{port}", "steady", fast=True, seed=1)
        robot.start(14.0)
        assert wait_for(lambda: robot.client.executed > 20, timeout=10)
        first.send_signal(signal.SIGTERM)
        assert first.wait(timeout=30) == 0
        assert "replicas keep serving" in (tmp_path / "front1.log").read_text()
        executed = robot.client.executed
        # served by its replica while no front runs
        assert wait_for(lambda: robot.client.executed > executed + 30, timeout=10)
        second = start_front(planner, port, tmp_path / "front2.log", ray_head)
        assert wait_for(lambda: "front listening" in (tmp_path / "front2.log").read_text(), timeout=120)
        log = (tmp_path / "front2.log").read_text()
        assert "robots=steady" in log  # the new front found the replicas by name, with the robot on one
        assert "did not take the front's forwarding key" not in log  # they took the new front's key, over Ray
        stats = robot.join()
        assert robot.client.reconnects == 0 and stats["outages_s"] == []
        assert stats["starvation_pct"] < 10.0, stats
    finally:
        for proc in (first, second):
            if proc is not None and proc.poll() is None:
                proc.kill()
