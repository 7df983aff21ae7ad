"""``benchmarks/vs_lerobot_async.py``'s timing parity: both systems are given the same robots'
timing for any ``--chunk`` and the same starvation window (``--settle_chunks``), and a policy that
cannot serve that timing is refused before anything starts. (The comparison itself runs minutes:
it is a benchmark, not a test.)"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture(scope="module")
def vs():
    sys.path.insert(0, str(BENCHMARKS))  # it imports its neighbours (_stock_async) by name
    try:
        spec = importlib.util.spec_from_file_location("vs_lerobot_async", BENCHMARKS / "vs_lerobot_async.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module  # its dataclasses look their module up there
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop("vs_lerobot_async", None)
        sys.path.remove(str(BENCHMARKS))


def test_ours_asks_after_the_steps_stock_asks_after_for_any_chunk(vs):
    """Stock asks once ``left / chunk <= 0.5``; ours, after ``h_min`` executed steps: the same tick,
    odd chunks included (``chunk // 2`` would make ours ask a step early at 7)."""
    for chunk in range(2, 61):
        h_min = vs.h_min_of(chunk)
        left = chunk - h_min
        assert left / chunk <= vs.THRESHOLD < (left + 1) / chunk, chunk
    assert (vs.h_min_of(10), vs.h_min_of(50), vs.h_min_of(7)) == (5, 25, 4)


@pytest.mark.subprocess
def test_both_sides_get_the_runs_timing_and_window(vs, tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"type": "pi05", "chunk_size": 50, "n_action_steps": 50}))
    opts = vs.parse_args(["--chunk=50", "--settle_chunks=3", f"--policy={tmp_path}", "--robots=1"])
    spec = vs.robot_spec(opts, 0, "127.0.0.1:1", tmp_path)
    # ours reads h_min/h_max, stock actions_per_chunk/chunk_size_threshold; both read settle_chunks
    assert (spec["h_min"], spec["h_max"], spec["actions_per_chunk"]) == (25, 50, 50)
    assert spec["chunk_size_threshold"] == 0.5 and spec["settle_chunks"] == 3 and spec["policy_type"] == "pi05"
    (tmp_path / "model.safetensors").write_bytes(b"weights")  # the header hashes them
    page = vs.notes({**vs.report_header(opts, "cmd"), "runs": []})
    assert "chunk 50, a new chunk after 25 executed steps" in page and "chunk number 3 on" in page


def test_a_policy_with_shorter_chunks_than_the_robots_is_refused(vs, tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"type": "pi05", "chunk_size": 50, "n_action_steps": 10}))
    with pytest.raises(vs.RunFailed, match=r"--chunk=50 .*n_action_steps=10"):
        vs.check_policy_chunk(str(tmp_path), 50)
    vs.check_policy_chunk(str(tmp_path), 10)  # within both: accepted
    for bad in (["--chunk=1"], ["--settle_chunks=0"]):
        with pytest.raises(SystemExit):
            vs.parse_args(bad)


def test_without_a_gpu_the_gpu_memory_column_reads_not_measured(vs, monkeypatch):
    def no_nvidia_smi(*args, **kwargs):
        raise FileNotFoundError("nvidia-smi")

    monkeypatch.setattr(subprocess, "run", no_nvidia_smi)
    assert vs.gpu_memory_used_bytes() is None
    assert vs.gib(None) == "–" and vs.gib(3 * 2**30) == "3.00"


def test_the_stock_server_adapter_hands_a_metaworld_policy_its_environment_state(vs):
    """Stock's client packs every float into ``observation.state``; the launcher's adapter splits
    the ``environment_state.*`` floats back out, in the robot's order, as our FeatureMap does."""
    pytest.importorskip("metaworld", reason="the metaworld extra is not installed")
    import _stock_async
    import numpy as np
    from lerobot.async_inference.helpers import map_robot_keys_to_lerobot_features, raw_observation_to_observation

    from lerobot_armory.robot.features import ENV_STATE, STATE, FeatureMap
    from lerobot_armory.robot.metaworld import MetaWorldRobot, MetaWorldRobotConfig

    robot = MetaWorldRobot(MetaWorldRobotConfig(task="push"))
    robot.connect()
    try:
        raw = robot.get_observation()
    finally:
        robot.disconnect()
    features = map_robot_keys_to_lerobot_features(robot)
    assert features[STATE]["shape"] == (43,)  # stock: 4 hand floats + 39 of the world, all "state"
    split = _stock_async.split_environment_state(raw_observation_to_observation)({**raw, "task": ""}, features, {})
    ours = FeatureMap.for_robot(robot.observation_features, robot.action_features).to_wire(raw)
    np.testing.assert_array_equal(split[STATE].numpy()[0], ours[STATE])
    np.testing.assert_array_equal(split[ENV_STATE].numpy()[0], ours[ENV_STATE])
    spec = {"robot_kind": "metaworld", "task": "push", "episodes": 3, "robot_id": "r0", "seed": 1000}
    assert _stock_async.robot_args(spec) == [
        "--robot.type=metaworld", "--robot.task=push", "--robot.episodes=3", "--robot.id=r0", "--robot.seed=1000",
    ]  # fmt: skip
