"""The static π0 sampler against LeRobot's own ``PI0Pytorch.sample_actions``: equal chunks at
every batch size with bucket padding, with and without RTC (fused; LeRobot's order at one size,
in float32 and bf16); one traced graph and no host synchronisation per bucket; the state row
padded like every input; bf16 chunks a bf16 rounding from float32, like LeRobot's; the registry
that picks a sampler per policy type."""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_armory.engine import rtc
from lerobot_armory.engine.options import EngineOptions, PolicyOptions
from lerobot_armory.engine.policy_engine import PolicyEngine
from tests.support.vla import three_steps, assert_padding_never_changes_a_real_row, assert_static_equals_lerobot, assert_traces_as_one_graph_with_no_host_sync
from tests.support.vla import rtc_batch as batch, sampler_inputs

RTC = rtc.RTCOptions(enabled=True, execution_horizon=8, delay_margin=0)


@pytest.fixture(scope="module")
def engines(pi0_dir):
    """LeRobot's π0 sampler and the static one (fused kernels, buckets 1, 2, 4, 8), both guided."""
    import torch

    torch.set_num_threads(1)
    lerobot = PolicyEngine(PolicyOptions(str(pi0_dir), "cpu"), RTC)
    static = PolicyEngine(PolicyOptions(str(pi0_dir), "cpu"), RTC, EngineOptions(static_sampler=True, graph_buckets="1,2,4,8"))
    static.warmup(8, log_progress=False)
    assert lerobot.sampler is None and static.sampler is not None and static.fused_kernels
    return lerobot, static




@pytest.mark.parametrize("b", range(1, 9))
def test_static_pi0_chunks_equal_lerobots_at_every_batch_size_padded_to_its_bucket(engines, b):
    """b = 3 runs as a padded batch of 4, b = 5..7 as 8: the real rows equal LeRobot's π0 sampler
    on the unpadded batch (fp32, 1e-5), unguided and guided per row."""
    lerobot, static = engines
    assert_static_equals_lerobot(lerobot, static, b)


def test_lerobots_order_of_operations_gives_lerobots_pi0_chunks(engines, pi0_dir):
    """``--engine.fused_kernels=false``: LeRobot's operations one for one (the time concatenated to
    every action, the state projected at every step in LeRobot, once here): within 1e-6."""
    lerobot, _ = engines
    ordered = PolicyEngine(PolicyOptions(str(pi0_dir), "cpu"), RTC, EngineOptions(static_sampler=True, fused_kernels=False))
    assert not ordered.fused_kernels
    obs, tasks, seeds, prefixes = batch(5, seed=3)
    np.testing.assert_allclose(ordered.infer_guided(obs, tasks, seeds, prefixes)[1], lerobot.infer_guided(obs, tasks, seeds, prefixes)[1], atol=1e-6, rtol=0)


def test_the_state_enters_through_its_token(engines):
    """π0's prompt is the task alone: the state reaches the chunk through the sampler's state
    input (a different state row, a different chunk, as in LeRobot)."""
    import torch

    _, static = engines
    inputs = sampler_inputs(static, 2)
    assert inputs.state is not None and inputs.state.shape == (2, static.config.max_state_dim)
    with torch.inference_mode():
        moved = inputs.with_tensors([t.clone() for t in inputs.tensors()])
        assert moved.state is not None
        moved.state[1, 0] += 0.5
        base, other = static.sampler.sample(inputs.padded(2)), static.sampler.sample(moved)
    assert torch.equal(base[0], other[0]) and (base[1] - other[1]).abs().max() > 1e-4


def test_padding_rows_and_a_hostile_state_never_change_a_real_rows_chunk(engines):
    """Three real rows padded to 4 with their own last row, or beside a row whose state, image,
    noise and leftover are extreme: the real rows' chunks are bit for bit the same."""
    _, static = engines
    assert_padding_never_changes_a_real_row(static)


@pytest.mark.slow
@pytest.mark.parametrize("guided", [False, True])
def test_the_whole_pi0_sampler_traces_as_one_graph_with_no_host_sync_at_every_bucket(engines, guided):
    """What predicts a CUDA graph capture, on the CPU: one dynamo graph, no break, no op waiting
    for the host, at every bucket; LeRobot's own π0 sampler, counted the same way, waits."""
    from lerobot_armory.acceleration.pi0_static import StaticPi0

    lerobot, static = engines
    with three_steps(static.policy):
        sampler = StaticPi0(static.policy, guided=guided, max_guidance_weight=RTC.max_guidance_weight)
    assert_traces_as_one_graph_with_no_host_sync(sampler, static, lerobot, guided)


def test_in_bf16_the_fused_pi0_stays_a_bf16_rounding_from_float32_like_lerobots(pi0_dir):
    """``--policy.dtype=bfloat16``: LeRobot's order keeps LeRobot's bf16 arithmetic (its chunks
    LeRobot's, 1e-6); the fused layers, float32 stream and last norm, are about as far
    from the float32 π0's chunks as LeRobot's own bf16 chunks (measured 0.6–1.3× here; π0 has no
    gates to damp its layers' bf16 products, unlike a random-weight π0.5), never twice as far."""
    bf16 = ["dtype=bfloat16"]
    float32 = PolicyEngine(PolicyOptions(str(pi0_dir), "cpu"))
    lerobot = PolicyEngine(PolicyOptions(str(pi0_dir), "cpu", overrides=bf16))
    fused = PolicyEngine(PolicyOptions(str(pi0_dir), "cpu", overrides=bf16), engine=EngineOptions(static_sampler=True))
    ordered = PolicyEngine(PolicyOptions(str(pi0_dir), "cpu", overrides=bf16), engine=EngineOptions(static_sampler=True, fused_kernels=False))
    assert fused.fused_kernels
    for b in (1, 3):
        obs, tasks, seeds, _ = batch(b)
        want, stock = float32.infer(obs, tasks, seeds), lerobot.infer(obs, tasks, seeds)
        np.testing.assert_allclose(ordered.infer(obs, tasks, seeds), stock, atol=1e-6, rtol=0)  # 0 measured
        ours, theirs = np.abs(fused.infer(obs, tasks, seeds) - want).max(), np.abs(stock - want).max()
        assert 0 < theirs < 1e-2 and ours <= 2 * theirs, (b, ours, theirs)


def test_each_policy_type_gets_its_own_static_sampler_or_a_reason(engines, pi05_dir):
    """The registry: π0 → StaticPi0, π0.5 → StaticPi05; each class refuses the other's policy, and
    a type with no static sampler is told which have one."""
    from lerobot_armory.acceleration import static_sampler
    from lerobot_armory.acceleration.pi0_static import StaticPi0
    from lerobot_armory.acceleration.pi05_static import StaticPi05

    _, static = engines
    pi05 = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"))
    assert static_sampler.sampler_class(static.policy) is StaticPi0
    assert static_sampler.sampler_class(pi05.policy) is StaticPi05
    assert static_sampler.unsupported_reason(static.policy) is None and static_sampler.unsupported_reason(pi05.policy) is None
    assert StaticPi05.unsupported_reason(static.policy) == "pi0 is not pi05"
    assert StaticPi0.unsupported_reason(pi05.policy) == "pi05 is not pi0"
    with pytest.raises(ValueError, match="pi0 is not pi05"):
        StaticPi05(static.policy)

    class Other:
        class config:  # noqa: N801
            type = "xvla"

    assert static_sampler.unsupported_reason(Other()) == "xvla has no static sampler yet (pi05, pi0, smolvla only); it is served by LeRobot's own sampler"
    assert "static sampler, buckets 1,2,4,8" in static.description


@pytest.mark.slow
def test_a_compiled_pi0_sampler_gives_the_same_chunks(pi0_dir, engines):
    """``--engine.compile_sampler=true`` on π0 (its expert layer takes no time conditioning):
    the layer-by-layer compiled sampler's chunks equal the uncompiled one's (1e-5)."""
    _, static = engines
    compiled = PolicyEngine(PolicyOptions(str(pi0_dir), "cpu"), RTC, EngineOptions(static_sampler=True, compile_sampler=True, graph_buckets="1,2"))
    compiled.warmup(2, log_progress=False)
    for b in (1, 2):
        obs, tasks, seeds, prefixes = batch(b, seed=2)
        np.testing.assert_allclose(compiled.infer_guided(obs, tasks, seeds, prefixes)[1], static.infer_guided(obs, tasks, seeds, prefixes)[1], atol=1e-5, rtol=0)


@pytest.mark.parametrize("kind", ["pi0_dir", "pi05_dir", "smolvla_dir"])
def test_placeholder_cameras_are_not_on_the_wire_and_are_filled_as_lerobot_fills_them(kind, request):
    """``--policy.empty_cameras=1`` adds an ``observation.images.empty_camera_0`` feature that no
    robot has: it is not a wire feature, and LeRobot's own image step fills it (−1 pixels, masked)
    in both samplers, so the chunks are those of ``predict_action_chunk`` on a batch without it
    (before: robots had to send a 480×640 frame, served as a real camera)."""
    import torch

    path = str(request.getfixturevalue(kind))
    options = PolicyOptions(path, "cpu", overrides=["empty_cameras=1"])
    lerobot = PolicyEngine(options)
    static = PolicyEngine(options, engine=EngineOptions(static_sampler=True, graph_buckets="1,2,4"))
    assert "observation.images.empty_camera_0" in lerobot.config.image_features
    assert all("empty_camera" not in spec.name for spec in lerobot.wire_features + static.wire_features)
    obs, tasks, seeds, _ = batch(3, seed=1)
    ours = lerobot.infer(obs, tasks, seeds)
    np.testing.assert_allclose(static.infer(obs, tasks, seeds), ours, atol=1e-5, rtol=0)
    with torch.inference_mode():  # what LeRobot's image step then sees: no placeholder, so it fills one
        processed = lerobot.preprocessor({**lerobot.to_batch(obs), "task": tasks})
        images, masks = (lerobot.policy.prepare_images if kind == "smolvla_dir" else lerobot.policy._preprocess_images)(processed)
    assert "observation.images.empty_camera_0" not in processed and len(images) == 2
    assert bool((images[1] == -1).all()) and not bool(masks[1].any())


@pytest.mark.parametrize("kind", ["pi0_dir", "pi05_dir", "smolvla_dir"])
def test_every_served_batch_has_a_prompt_length_a_graph_was_recorded_for(kind, request):
    """A CUDA graph holds one prompt length, and a batch whose length has none is served eagerly
    (on a GPU: several times slower). π0 and π0.5 pad every prompt to the tokenizer's max length;
    SmolVLA pads a batch to its longest prompt (before: a new length nearly every batch, and graphs
    recorded at the warm-up prompt's). Every batch, prompts from one word to past the max length,
    is fitted to a length warm-up records (``_example_inputs``), the chunks stay LeRobot's, and
    the profile times the longest."""
    import torch

    path = str(request.getfixturevalue(kind))
    lerobot = PolicyEngine(PolicyOptions(path, "cpu"))
    static = PolicyEngine(PolicyOptions(path, "cpu"), engine=EngineOptions(static_sampler=True, graph_buckets="1,2,4"))
    static.warmup(4, log_progress=False)
    full = static.config.tokenizer_max_length
    assert static.prompt_buckets == (16, 32, full)[: 3 if full > 32 else 2]  # auto: 16 and 32 for a short prompt
    recorded = {inputs.prompt_length for inputs in static._example_inputs(2)}
    assert recorded == set(static.prompt_buckets)
    # The length the pre-processor's tokenizer pads to is the one that counts: the config's field
    # does not reach the saved tokenizer step, so an override of it changes nothing here.
    overridden = PolicyEngine(PolicyOptions(path, "cpu", overrides=[f"tokenizer_max_length={full // 2}"]), engine=EngineOptions(static_sampler=True))
    assert overridden.prompt_buckets == static.prompt_buckets
    served = []
    for words in (1, 3, 6, 12, 40):
        obs, _, seeds, _ = batch(2, seed=words)
        tasks = ["pick " * words, "up"]
        with torch.inference_mode():
            processed = static.preprocessor({**static.to_batch(obs), "task": tasks})
            length = static._sampler_inputs(processed, {"noise": static._noise(seeds)}).prompt_length
        assert length in recorded, (words, length, recorded)
        served.append(length)
        np.testing.assert_allclose(static.infer(obs, tasks, seeds), lerobot.infer(obs, tasks, seeds), atol=1e-5, rtol=0)
    assert len(set(served)) > 1  # short prompts ran shorter
    seen: list[int] = []
    sample = static.sampler.sample
    static.sampler.sample = lambda inputs: (seen.append(inputs.prompt_length), sample(inputs))[1]
    static.profile(2, warmup=0, reps=1, log_progress=False)
    assert seen and set(seen) == {full}
