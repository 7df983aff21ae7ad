"""Policies that read an observation history (``n_obs_steps = 2``: diffusion through its input,
VQ-BeT and multi-task DiT through their queues) served live to several robots sharing batches:
every chunk is the one its robot's own last two observations give alone; and the openpi
endpoint, whose clients send one observation per request, refuses them."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

from lerobot_armory.engine.options import PolicyOptions
from lerobot_armory.engine.policy_engine import PolicyEngine
from lerobot_armory.engine.protocol import noise_seed
from lerobot_armory.errors import ConfigError
from lerobot_armory.engine.coverage import frozen_chance
from lerobot_armory.demo.build import make_demo_policy
from lerobot_armory.demo.config import DemoPolicyConfig
from lerobot_armory.serving.config import OpenpiOptions
from tests.support.vla import TASKS, observation, serve_prompt_robots


@pytest.fixture(scope="module", params=["diffusion", "vqbet", "multi_task_dit"])
def engine(request, tmp_path_factory):
    """The policy, with chance frozen while it serves when it draws for the whole batch (VQ-BeT,
    multi-task DiT): the check is then of each row's history alone."""
    out = tmp_path_factory.mktemp(request.param) / "policy"
    make_demo_policy(DemoPolicyConfig(output=str(out), kind=request.param, chunk_size=10, state_dim=2, image_size=64))
    engine = PolicyEngine(PolicyOptions(str(out), "cpu"))
    with frozen_chance() if engine.kind.randomness(engine.config).startswith("drawn per batch") else contextlib.nullcontext():
        yield engine


def history(k: int, index: int) -> list[dict[str, np.ndarray]]:
    """What robot k's last two ticks were at ``index`` (the first observation repeated at 0)."""
    return [observation(k, max(0, index - 1)), observation(k, index)]


def test_the_policy_reads_two_observations_and_the_earlier_one_matters(engine):
    assert engine.history_steps == 2
    now = observation(0, 5)
    a = engine.infer([now], [TASKS[0]], [1], [history(0, 5)])
    b = engine.infer([now], [TASKS[0]], [1], [[observation(1, 4), now]])
    assert np.abs(a - b).max() > 1e-4


def test_shared_batches_give_each_robot_the_chunk_of_its_own_history(engine):
    server, robots = serve_prompt_robots(engine, list(TASKS))
    by_id = {r.robot_id: r for r in robots}
    checked = 0
    for record in server.batch_log:
        if len(record.robots) < 2 or not record.ok:
            continue
        for robot_id, i_start in zip(record.robots, record.i_starts, strict=True):
            robot = by_id[robot_id]
            chunk = next((c for c in robot.chunks if c.i_start == i_start), None)
            if chunk is None:
                continue
            seed = noise_seed(robot.robot_id, chunk.chunk_id)
            alone = engine.infer([observation(robot.k, i_start)], [robot.task], [seed], [history(robot.k, i_start)])[0]
            np.testing.assert_allclose(chunk.actions, alone, atol=1e-5)
            checked += 1
    assert checked >= 3


def test_the_openpi_endpoint_refuses_a_history_policy(engine):
    from lerobot_armory.entrypoints.grpc.service import PolicyInfo
    from lerobot_armory.entrypoints.server import ArmoryServer
    from lerobot_armory.inference_latency import LatencyProfile
    from lerobot_armory.schedulers import EarliestDeadlineConfig

    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    server = ArmoryServer(engine, info, LatencyProfile("t", (10.0, 12.0)), EarliestDeadlineConfig(), 2, port=0)
    with pytest.raises(ConfigError, match="last 2 observations of each robot"):
        server.serve_openpi(OpenpiOptions(port=0))
