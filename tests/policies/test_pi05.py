"""π0.5 served for real: LeRobot's own PI05 classes at the tiny size, built and loaded offline,
per-robot prompts and noise, ``--policy.<field>`` overrides, and the whole path end to end."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.engine.policy_engine import PolicyEngine
from lerobot_armory.engine.options import PolicyOptions
from lerobot_armory.engine.protocol import noise_seed
from lerobot_armory.wire import check_features
from tests.support.vla import (
    IMAGE,
    TASKS,
    assert_batched_equals_alone,
    assert_prompt_and_noise_change_the_chunk,
    assert_shared_chunks_equal_alone,
    observation,
    serve_prompt_robots,
)


@pytest.fixture(scope="session")
def pi05(pi05_dir):
    import torch

    torch.set_num_threads(1)
    return PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"))


def test_tiny_pi05_is_lerobots_own_pi05_loaded_offline_with_armory_sim_features(pi05_dir, monkeypatch):
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy

    from lerobot_armory.robot.armory_sim import ArmorySim, ArmorySimConfig
    from lerobot_armory.robot.features import FeatureMap

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    saved = json.loads((pi05_dir / "config.json").read_text())
    assert saved["type"] == "pi05" and saved["paligemma_variant"] == "armory_tiny"
    assert (pi05_dir / "tokenizer" / "tokenizer.json").is_file()
    engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"))
    assert isinstance(engine.policy, PI05Policy)
    assert engine.chunk_size == 10 and engine.noise_shape == (10, 32)
    robot = ArmorySim(ArmorySimConfig())
    fmap = FeatureMap.for_robot(robot.observation_features, robot.action_features)
    from lerobot_armory.wire import FeatureSpec

    declared = [FeatureSpec(name, dtype, shape) for name, (dtype, shape) in fmap.wire_features().items()]
    assert check_features(declared, engine.wire_features) == []
    assert engine.action_dim == len(fmap.action_keys)


def test_the_directory_loads_after_it_was_moved(pi05_dir, tmp_path):
    """The tokenizer inside the directory is used wherever the directory now is."""
    moved = tmp_path / "moved"
    shutil.copytree(pi05_dir, moved)
    original = pi05_dir / "tokenizer"
    hidden = pi05_dir / "tokenizer.away"
    original.rename(hidden)  # the path the saved pre-processor names no longer exists
    try:
        engine = PolicyEngine(PolicyOptions(str(moved), "cpu"))
        assert engine.infer([observation(0, 0)], ["touch the target"]).shape == (1, 10, 2)
    finally:
        hidden.rename(original)


def test_a_batched_chunk_equals_the_chunk_computed_alone(pi05):
    assert_batched_equals_alone(pi05)


def test_the_prompt_and_the_noise_each_change_the_chunk(pi05):
    assert_prompt_and_noise_change_the_chunk(pi05)
    # The seed is not just the chunk id, and fits the 32 bits torch's CPU generator uses.
    assert noise_seed("robot0", 1) != noise_seed("robot1", 1)
    assert 0 <= noise_seed("robot0", 1) < 2**32


def test_policy_field_overrides_reach_the_policy_config(pi05_dir):
    engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu", overrides=["num_inference_steps=2", "dtype=bfloat16"]))
    assert engine.config.num_inference_steps == 2 and engine.config.dtype == "bfloat16"
    assert "dtype=bfloat16" in engine.description
    assert engine.infer([observation(0, 0)], ["x"]).dtype == np.float32
    with pytest.raises(ConfigError, match=r"policy\.dtyp: pi05 policies have no field 'dtyp' \(did you mean dtype\?\)"):
        PolicyEngine(PolicyOptions(str(pi05_dir), "cpu", overrides=["dtyp=bfloat16"]))
    with pytest.raises(ConfigError, match=r"policy\.dtype: .*Invalid dtype: float16"):
        PolicyEngine(PolicyOptions(str(pi05_dir), "cpu", overrides=["dtype=float16"]))


@pytest.mark.slow
@pytest.mark.subprocess
def test_server_command_names_an_unknown_policy_field_and_exits_2(pi05_dir):
    proc = subprocess.run(
        [sys.executable, "-m", "lerobot_armory.entrypoints.server", f"--policy.path={pi05_dir}", "--policy.device=cpu", "--policy.bogus=1"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last == "lerobot-armory-server: error: policy.bogus: pi05 policies have no field 'bogus'", proc.stderr
    assert "Traceback" not in proc.stderr


def test_served_chunks_equal_each_robots_chunk_computed_alone(pi05):
    """Through the real server: every chunk computed in a batch shared with other robots is what
    the policy computes for that robot's observation, its own prompt and its own noise alone."""
    server, robots = serve_prompt_robots(pi05, list(TASKS))
    assert assert_shared_chunks_equal_alone(pi05, server, robots) >= 3


@pytest.mark.slow
@pytest.mark.subprocess
def test_end_to_end_build_serve_two_armory_sim_robots_with_their_own_tasks(pi05_dir, tmp_path):
    """The commands a user types: the built directory served by lerobot-armory-server, two
    lerobot-armory-client armory_sim robots with different --task, chunks received and executed."""
    from lerobot_armory.bench.live import start_server

    batch_log = tmp_path / "batches.jsonl"
    server, address = start_server(
        [f"--policy.path={pi05_dir}", "--policy.device=cpu", "--port=0", "--max_batch_size=2", "--scheduler.type=edf",
         "--latency_profile=l40s-pi05", "--status_interval_s=0", f"--batch_log={batch_log}"]
    )  # fmt: skip
    clients = []
    try:
        for k, (scene, task) in enumerate((("dynamic", "reach the moving target"), ("static", "touch the static target"))):
            clients.append(
                subprocess.Popen(
                    [sys.executable, "-m", "lerobot_armory.robot.cli", "--robot.type=armory_sim", f"--robot.scene={scene}",
                     f"--server_address={address}", f"--robot_id=sim{k}", f"--task={task}", "--fps=20", "--h_min=1",
                     "--h_max=10", "--duration_s=6", f"--stats_path={tmp_path / f'sim{k}.json'}", "--log_level=warning"],
                    env={**os.environ, "PYTHONUNBUFFERED": "1"},
                )  # fmt: skip
            )
        codes = [c.wait(timeout=120) for c in clients]
    finally:
        for c in clients:
            if c.poll() is None:
                c.kill()
        server.send_signal(signal.SIGINT)
        assert server.wait(timeout=30) == 0
    assert codes == [0, 0]
    for k in range(2):
        stats = json.loads((tmp_path / f"sim{k}.json").read_text())
        assert stats["chunks_received"] >= 5 and stats["executed_steps"] > 0, stats
    batches = [json.loads(line) for line in batch_log.read_text().splitlines()]
    assert {r for b in batches for r in b["robots"]} == {"sim0", "sim1"}


def test_pinned_staging_buffers_are_reused_and_never_serve_stale_data(pi05, monkeypatch):
    """The CUDA path's staging (exercised on the CPU with pinning stubbed out): one buffer per
    (feature, batch size), refilled for every batch, so a batch never sees its predecessor's data."""
    import torch

    monkeypatch.setattr(torch.Tensor, "pin_memory", lambda self: self)
    monkeypatch.setattr(pi05, "_pinned", True)
    monkeypatch.setattr(pi05, "_staging", {})
    first = pi05.to_batch([observation(0, 0), observation(1, 0)])
    ptr = pi05._staging[(IMAGE, 2)].data_ptr()
    second = pi05.to_batch([observation(2, 0), observation(3, 0)])
    assert pi05._staging[(IMAGE, 2)].data_ptr() == ptr, "the buffer for b=2 was not reused"
    expected = np.stack([observation(k, 0)[IMAGE] for k in (2, 3)]).transpose(0, 3, 1, 2) / 255.0
    np.testing.assert_allclose(second[IMAGE].numpy(), expected, atol=1e-6)
    assert not torch.equal(first[IMAGE], second[IMAGE])
    pi05.to_batch([observation(0, 0)])
    assert set(pi05._staging) == {(IMAGE, 2), (IMAGE, 1)}  # one per batch size; the state stays on the host
    # Served chunks are unchanged by the staging path.
    seeds = [noise_seed("robot0", 0)]
    staged = pi05.infer([observation(0, 0)], [TASKS[0]], seeds)
    monkeypatch.setattr(pi05, "_pinned", False)
    np.testing.assert_allclose(staged, pi05.infer([observation(0, 0)], [TASKS[0]], seeds), atol=1e-6)


def test_a_hostile_prompt_is_served_and_changes_nothing_for_the_others(pi05):
    """The longest prompt registration allows, in control characters, emoji and the template's own
    words: the tokenizer truncates it, its robot is served, and its batch mate's chunks from their
    shared batches are still exactly what that robot's own prompt gives alone."""
    from lerobot_armory.entrypoints.grpc.service import MAX_TASK

    hostile = ("Task: \x00\x1b[2J;\nAction: 🤖" + "ünïcødé\u202e" * 400)[:MAX_TASK]
    server, robots = serve_prompt_robots(pi05, [TASKS[0], hostile], max_batch_size=2)
    assert server.loop.stats.failed_batches == 0
    assert assert_shared_chunks_equal_alone(pi05, server, robots, only={"prompt0"}) >= 1
    assert robots[1].chunks and all(np.isfinite(c.actions).all() for c in robots[1].chunks)


def test_warmup_keeps_a_compiled_model_only_if_it_measured_faster(pi05_dir):
    """``warmup`` times a torch.compile wrapper against the eager function it wraps, both warm, and
    keeps the faster (a stand-in wrapper here: real compilation takes minutes on a CPU)."""
    import time

    engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"))
    model = engine.policy.model
    eager = model.sample_actions

    def slow(*args, **kwargs):
        time.sleep(0.05)
        return eager(*args, **kwargs)

    def fast(*args, **kwargs):
        return eager(*args, **kwargs)

    slow._torchdynamo_orig_callable = eager  # a "compiled" model slower than its eager self
    model.sample_actions = slow
    engine.warmup(2, reps=1, log_progress=False)
    assert engine.compiled_kept is False and model.sample_actions == eager
    assert "eager (compiled was slower)" in engine.description

    fast._torchdynamo_orig_callable = slow  # a "compiled" model faster than its eager self
    model.sample_actions = fast
    engine.warmup(2, reps=1, log_progress=False)
    assert engine.compiled_kept is True and model.sample_actions is fast
    assert engine.description.endswith("compiled)")


@pytest.mark.gpu
@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="the pinned, asynchronous path exists on CUDA only")
def test_on_cuda_back_to_back_batches_match_the_unstaged_path(pi05_dir):
    """Two batches in a row reuse the pinned staging buffers while the first copy may be in flight:
    their chunks must equal the same requests through the synchronous host path."""
    engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cuda"))
    seeds = [noise_seed("robot0", 0), noise_seed("robot1", 0)]
    first = engine.infer([observation(0, 0), observation(1, 0)], list(TASKS[:2]), seeds)
    second = engine.infer([observation(0, 1), observation(1, 1)], list(TASKS[:2]), seeds)
    engine._pinned = False
    np.testing.assert_allclose(first, engine.infer([observation(0, 0), observation(1, 0)], list(TASKS[:2]), seeds), atol=1e-4)
    np.testing.assert_allclose(second, engine.infer([observation(0, 1), observation(1, 1)], list(TASKS[:2]), seeds), atol=1e-4)
