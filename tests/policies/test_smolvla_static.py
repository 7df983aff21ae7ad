"""The static SmolVLA sampler against LeRobot's own ``VLAFlowMatching.sample_actions``: equal
chunks at every batch size with bucket padding, with and without RTC, with LeRobot's optional
prefix padding and image tokens; one traced graph and no host synchronisation per bucket where
LeRobot's sampler waits; padding rows that cannot touch real ones; the options it refuses."""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_armory.engine import rtc
from lerobot_armory.engine.options import EngineOptions, PolicyOptions
from lerobot_armory.engine.policy_engine import PolicyEngine
from lerobot_armory.errors import ConfigError
from tests.support.vla import three_steps, TASKS, assert_padding_never_changes_a_real_row, assert_shared_chunks_equal_alone, assert_static_equals_lerobot
from tests.support.vla import assert_traces_as_one_graph_with_no_host_sync, serve_prompt_robots
from tests.support.vla import assert_unwritten_memory_never_reaches_a_chunk, sampler_inputs
from tests.support.vla import rtc_batch as batch

RTC = rtc.RTCOptions(enabled=True, execution_horizon=8, delay_margin=0)


@pytest.fixture(scope="module")
def engines(smolvla_dir):
    """LeRobot's SmolVLA sampler and the static one (buckets 1, 2, 4, 8), both guided."""
    import torch

    torch.set_num_threads(1)
    lerobot = PolicyEngine(PolicyOptions(str(smolvla_dir), "cpu"), RTC)
    static = PolicyEngine(PolicyOptions(str(smolvla_dir), "cpu"), RTC, EngineOptions(static_sampler=True, graph_buckets="1,2,4,8"))
    static.warmup(8, log_progress=False)
    assert lerobot.sampler is None and static.sampler is not None
    return lerobot, static




@pytest.mark.parametrize("b", range(1, 9))
def test_static_smolvla_chunks_equal_lerobots_at_every_batch_size_padded_to_its_bucket(engines, b):
    """b = 3 runs as a padded batch of 4, b = 5..7 as 8: the real rows equal LeRobot's SmolVLA
    on the unpadded batch (fp32, 1e-5; bit for bit on this CPU at most sizes), unguided and
    guided per row. The tiny SmolVLA has a self-attention and a cross-attention layer."""
    lerobot, static = engines
    assert static.sampler.sample.__self__.self_attention == [True, False]  # both kinds of expert layer run
    assert_static_equals_lerobot(lerobot, static, b)


def test_lerobots_order_of_operations_gives_lerobots_smolvla_chunks(engines, smolvla_dir):
    """``--engine.fused_kernels=false``: LeRobot's and HF's operations one for one (the fused
    kernels are the default and the tests above hold them to 1e-5): within 1e-6, guided."""
    lerobot, static = engines
    assert static.fused_kernels
    ordered = PolicyEngine(PolicyOptions(str(smolvla_dir), "cpu"), RTC, EngineOptions(static_sampler=True, fused_kernels=False))
    assert not ordered.fused_kernels
    obs, tasks, seeds, prefixes = batch(5, seed=3)
    want = lerobot.infer_guided(obs, tasks, seeds, prefixes)[1]
    np.testing.assert_allclose(ordered.infer_guided(obs, tasks, seeds, prefixes)[1], want, atol=1e-6, rtol=0)


@pytest.mark.parametrize("override", ["prefix_length=200", "add_image_special_tokens=true"])
def test_lerobots_prefix_padding_and_image_tokens_give_the_same_chunks(smolvla_dir, override):
    """SmolVLA's options that change the prefix: padded to a fixed length (masked padding) and
    the special image tokens around each camera's embeddings (made once, on the device)."""
    lerobot = PolicyEngine(PolicyOptions(str(smolvla_dir), "cpu", overrides=[override]))
    static = PolicyEngine(PolicyOptions(str(smolvla_dir), "cpu", overrides=[override]), engine=EngineOptions(static_sampler=True, graph_buckets="1,4"))
    obs, tasks, seeds, _ = batch(3, seed=5)
    np.testing.assert_allclose(static.infer(obs, tasks, seeds), lerobot.infer(obs, tasks, seeds), atol=1e-5, rtol=0)


def test_padding_rows_and_a_hostile_row_never_change_a_real_rows_chunk(engines):
    """Three real rows padded to 4 with their own last row, or beside a row whose state, image,
    noise and leftover are extreme: the real rows' chunks are bit for bit the same."""
    _, static = engines
    assert_padding_never_changes_a_real_row(static)


@pytest.mark.slow
@pytest.mark.parametrize("guided", [False, True])
def test_the_whole_smolvla_sampler_traces_as_one_graph_with_no_host_sync_at_every_bucket(engines, guided):
    """What predicts a CUDA graph capture, on the CPU: one dynamo graph, no break, no op waiting
    for the host, at every bucket (vision tower, prefix, ten steps, RTC); LeRobot's own SmolVLA
    sampler, counted the same way, waits (tensors made from Python data at every step)."""
    from lerobot_armory.acceleration.smolvla_static import StaticSmolVLA

    lerobot, static = engines
    with three_steps(static.policy):
        sampler = StaticSmolVLA(static.policy, guided=guided, max_guidance_weight=RTC.max_guidance_weight)
    assert_traces_as_one_graph_with_no_host_sync(sampler, static, lerobot, guided)


def test_what_the_smolvla_sampler_does_not_do_yet_is_refused_in_one_line(smolvla_dir):
    """SDPA attention, a compiled sampler and a bf16 vision cast are π0-family options: refused
    with the option named, not silently ignored; fused kernels are the default, and
    ``--engine.fused_kernels=false`` runs LeRobot's order."""
    path = str(smolvla_dir)
    with pytest.raises(ConfigError, match="static sampler cannot run it.*eager"):
        PolicyEngine(PolicyOptions(path, "cpu"), engine=EngineOptions(static_sampler=True, attention="sdpa"))
    with pytest.raises(ConfigError, match="engine.compile_sampler.*smolvla's static sampler is not compiled yet"):
        PolicyEngine(PolicyOptions(path, "cpu"), engine=EngineOptions(static_sampler=True, compile_sampler=True))
    with pytest.raises(ConfigError, match="vision tower"):
        PolicyEngine(PolicyOptions(path, "cpu"), engine=EngineOptions(static_sampler=True, vision_dtype="bfloat16"))
    # ALOHA's conversions run around LeRobot's sampler (predict_action_chunk): not skipped silently.
    with pytest.raises(ConfigError, match="engine.static_sampler.*adapt_to_pi_aloha"):
        PolicyEngine(PolicyOptions(path, "cpu", overrides=["adapt_to_pi_aloha=true"]), engine=EngineOptions(static_sampler=True))
    engine = PolicyEngine(PolicyOptions(path, "cpu"), engine=EngineOptions(static_sampler=True))
    assert engine.fused_kernels and "fused kernels" in engine.description
    ordered = PolicyEngine(PolicyOptions(path, "cpu"), engine=EngineOptions(static_sampler=True, fused_kernels=False))
    assert not ordered.fused_kernels and "static sampler" in ordered.description


@pytest.mark.parametrize("part", ["vlm", "all"])
def test_a_bf16_smolvlm_gives_lerobots_chunks_bit_for_bit(smolvla_dir, part):
    """A real SmolVLA loads its SmolVLM in bf16 (``torch_dtype="bfloat16"``) beside a float32
    expert; LeRobot then concatenates the expert's float32 suffix keys onto the VLM's bf16 prefix
    keys (promoted to float32), and the static cache holds them in that promoted dtype, so the
    chunks in LeRobot's order are LeRobot's exactly (a bf16 cache rounded the suffix's keys: 7.5e-5
    off). The fused kernels round differently (one rounding per fused norm, float32 rotary and
    queries): their chunks are as near the float32 model's as LeRobot's bf16 ones (0.84× and 0.99×
    LeRobot's distance measured; held to 1.5×)."""
    import torch
    from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS

    from lerobot_armory.acceleration.pi05_static import SamplerInputs
    from lerobot_armory.acceleration.smolvla_static import StaticSmolVLA

    engine = PolicyEngine(PolicyOptions(str(smolvla_dir), "cpu"))
    obs, tasks, seeds, _ = batch(3, seed=2)
    with torch.inference_mode():
        processed = engine.preprocessor({**engine.to_batch(obs), "task": tasks})
        noise = engine._noise(seeds)
        float32 = engine.policy.predict_action_chunk(processed, noise=noise)
    vwe = engine.policy.model.vlm_with_expert
    (vwe.vlm if part == "vlm" else vwe).to(torch.bfloat16)
    sampler = StaticSmolVLA(engine.policy, fused=False)
    fused = StaticSmolVLA(engine.policy)
    assert fused.fused and not sampler.fused
    with torch.inference_mode():
        want = engine.policy.predict_action_chunk(processed, noise=noise)
        images = tuple(processed[k] for k in engine.config.image_features)
        inputs = SamplerInputs(images, processed[OBS_LANGUAGE_TOKENS], processed[OBS_LANGUAGE_ATTENTION_MASK], noise, state=engine.policy.prepare_state(processed))
        got = sampler.sample(inputs)[:, :, : want.shape[2]]
        near = fused.sample(inputs)[:, :, : want.shape[2]]
    assert torch.equal(got, want), (got - want).abs().max()
    lerobot_error, fused_error = float((want - float32).abs().max()), float((near - float32).abs().max())
    assert 0 < fused_error <= 1.5 * lerobot_error, (fused_error, lerobot_error)


def test_served_through_the_fused_sampler_each_robots_chunk_is_lerobots_chunk_alone(smolvla_dir):
    """A real server on the static SmolVLA (fused kernels; buckets 1 and 3, so a batch of two is
    padded) and three robots whose prompts differ in length share batches (each batch's prompts
    fitted to a prompt bucket, where LeRobot pads to the batch's longest): every shared chunk
    equals LeRobot's SmolVLA on that robot's observation, prompt and noise alone."""
    lerobot = PolicyEngine(PolicyOptions(str(smolvla_dir), "cpu"))
    static = PolicyEngine(PolicyOptions(str(smolvla_dir), "cpu"), engine=EngineOptions(static_sampler=True, graph_buckets="1,3"))
    static.warmup(3, log_progress=False)
    assert static.fused_kernels and static.sampler.buckets == (1, 3)
    server, robots = serve_prompt_robots(static, list(TASKS), max_batch_size=3)
    assert server.loop.stats.failed_batches == 0
    assert assert_shared_chunks_equal_alone(lerobot, server, robots) >= 1


def test_the_fused_prefix_and_caches_are_multiples_of_8_and_unwritten_memory_never_reaches_a_chunk(engines):
    """The fused SmolVLA pads its prefix (LeRobot's own padding: zeros, masked) and its caches (masked
    zeros after the suffix) to multiples of ``KEY_ALIGN`` positions, for cuBLAS's Hopper kernels.
    With every fresh allocation of the sample filled with NaN (what a GPU's reused memory may hold),
    the chunks are the same; LeRobot's order keeps LeRobot's lengths."""
    import torch

    from lerobot_armory.acceleration.pi05_kernels import KEY_ALIGN
    from lerobot_armory.acceleration.smolvla_static import StaticSmolVLA

    _, static = engines
    fused = static.sampler.sample.__self__
    ordered = StaticSmolVLA(fused.policy, guided=True, fused=False)
    assert fused.fused and not ordered.fused
    inputs = sampler_inputs(static, 3, seed=7, horizon=RTC.execution_horizon)
    with torch.no_grad():
        fused.prepare(), ordered.prepare()  # the per-policy constants, made before memory turns to NaN
        vision = fused.vision(inputs.images)
        p = fused._embed_prefix(inputs, vision)[1].shape[1]
        lerobot_p = ordered._embed_prefix(inputs, ordered.vision(inputs.images))[1].shape[1]
        assert p % KEY_ALIGN == 0 and p > lerobot_p, (p, lerobot_p)  # padding to test
        length = fused.ops.cache_length(p, fused.chunk_size)
        assert length % KEY_ALIGN == 0 and length > p + fused.chunk_size, (length, p)  # a gap to test
    assert_unwritten_memory_never_reaches_a_chunk(fused, ordered, inputs)
