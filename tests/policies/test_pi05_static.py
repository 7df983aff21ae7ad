"""The static π0.5 sampler (the region a CUDA graph records) against LeRobot's own sampler: equal
chunks at every batch size with bucket padding, with and without RTC; one traced graph and no
host synchronisation per bucket; the bucket and engine plumbing around it."""

from __future__ import annotations

import numpy as np
import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.engine import rtc
from lerobot_armory.engine.cuda_graphs import BucketedSampler, bucket_for, parse_buckets
from lerobot_armory.engine.policy_engine import PolicyEngine
from lerobot_armory.engine.options import EngineOptions, PolicyOptions
from lerobot_armory.engine.protocol import noise_seed
from tests.support.vla import three_steps, TASKS, assert_shared_chunks_equal_alone, observation, serve_prompt_robots
from tests.support.vla import assert_padding_never_changes_a_real_row, assert_static_equals_lerobot, assert_traces_as_one_graph_with_no_host_sync
from tests.support.vla import assert_unwritten_memory_never_reaches_a_chunk, sampler_inputs
from tests.support.vla import rtc_batch as batch

BUCKETS = (1, 2, 4, 8)
RTC = rtc.RTCOptions(enabled=True, execution_horizon=8, delay_margin=0)


@pytest.fixture(scope="module")
def engines(pi05_dir):
    """LeRobot's sampler and the static sampler over the same policy directory, with RTC (a guided
    engine serves unguided batches too), the static one warmed up to buckets 1, 2, 4, 8."""
    import torch

    torch.set_num_threads(1)
    lerobot = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), RTC)
    static = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), RTC, EngineOptions(static_sampler=True, graph_buckets="1,2,4,8"))
    static.warmup(8, log_progress=False)
    assert lerobot.sampler is None and static.sampler is not None and static.sampler.buckets == BUCKETS
    return lerobot, static


@pytest.mark.parametrize("b", range(1, 9))
def test_static_chunks_equal_lerobots_at_every_batch_size_padded_to_its_bucket(engines, b):
    """b = 3 runs as a padded batch of 4, b = 5..7 as 8: the real rows equal LeRobot's sampler on
    the unpadded batch (fp32, 1e-5), unguided and guided (per-row RTC, rows without a prefix)."""
    lerobot, static = engines
    assert_static_equals_lerobot(lerobot, static, b)


def test_a_guided_row_equals_lerobots_stock_rtc_for_that_robot_alone(engines, pi05_dir):
    """The chain closed: a static guided batch row equals LeRobot's own RTCProcessor, one robot."""
    import torch

    from lerobot_armory.engine.loading import load_policy

    _, static = engines
    obs, tasks, seeds, prefixes = batch(3, seed=4)
    _, model_actions = static.infer_guided(obs, tasks, seeds, prefixes)
    config, policy, pre, _ = load_policy(str(pi05_dir), "cpu")
    config.rtc_config = RTC.lerobot_config()
    policy.init_rtc_processor()
    assert type(policy.model.rtc_processor).__name__ == "RTCProcessor"
    k = 1
    one = static.to_batch([obs[k]])
    one["task"] = [tasks[k]]
    kwargs = {"noise": static._noise([seeds[k]]), "inference_delay": prefixes[k].inference_delay,
              "prev_chunk_left_over": torch.from_numpy(prefixes[k].leftover)}  # fmt: skip
    with torch.no_grad():
        alone = policy.predict_action_chunk(pre(one), **kwargs)
    np.testing.assert_allclose(model_actions[k], alone[0].numpy(), atol=1e-5)


def test_padding_rows_never_change_a_real_rows_chunk(engines):
    """The same three real rows padded to 4 with their own last row, with another robot's row, or
    with extreme values: the real rows' chunks are bit for bit the same."""
    _, static = engines
    assert_padding_never_changes_a_real_row(static)


@pytest.mark.slow
@pytest.mark.parametrize("guided", [False, True])
def test_the_whole_sampler_traces_as_one_graph_with_no_host_sync_at_every_bucket(engines, guided):
    """What predicts a successful CUDA graph capture on a GPU, checked on the CPU: for every bucket,
    ``torch.compile(fullgraph=True)`` traces the whole sampler (vision tower, prefix, the
    denoising steps — three here, tests/support/vla.py's ``three_steps`` —, RTC) as one graph with no break, and no op in it waits for the host. LeRobot's
    own sampler, traced by the same counter, does wait (the check can fail)."""
    from lerobot_armory.acceleration.pi05_static import StaticPi05

    lerobot, static = engines
    with three_steps(static.policy):
        sampler = StaticPi05(static.policy, guided=guided, max_guidance_weight=RTC.max_guidance_weight)
    assert_traces_as_one_graph_with_no_host_sync(sampler, static, lerobot, guided)


def test_buckets_default_to_every_size_to_16_then_multiples_of_8_ending_at_the_cap():
    assert parse_buckets(None, 8) == (1, 2, 3, 4, 5, 6, 7, 8)
    assert parse_buckets(None, 5) == (1, 2, 3, 4, 5)
    assert parse_buckets(None, 40) == (*range(1, 17), 24, 32, 40)
    assert parse_buckets(None, 30) == (*range(1, 17), 24, 30)
    assert parse_buckets(None, 1) == (1,)
    assert parse_buckets("1, 3,16", 6) == (1, 3, 6)
    assert [bucket_for(b, (1, 2, 4, 8)) for b in range(1, 10)] == [1, 2, 4, 4, 8, 8, 8, 8, None]
    for bad in ("0,2", "two", ","):
        with pytest.raises(ConfigError, match="engine.graph_buckets"):
            parse_buckets(bad, 4)


def test_tf32_is_the_default_only_for_a_bf16_policy_on_a_cuda_device():
    auto = EngineOptions()
    assert auto.resolved_matmul_precision("cuda", "bfloat16") == "high"
    assert auto.resolved_matmul_precision("cuda:1", "bfloat16") == "high"
    assert auto.resolved_matmul_precision("cuda", "float32") == "highest"
    assert auto.resolved_matmul_precision("cpu", "bfloat16") == "highest"
    assert auto.resolved_matmul_precision("cuda", None) == "highest"
    assert EngineOptions(matmul_precision="highest").resolved_matmul_precision("cuda", "bfloat16") == "highest"
    with pytest.raises(ConfigError, match="engine.matmul_precision"):
        EngineOptions(matmul_precision="tf32").validate()


def test_the_vision_tower_is_bf16_by_default_only_for_a_bf16_policy_graphed_on_a_cuda_device():
    auto = EngineOptions()
    assert auto.resolved_vision_dtype("cuda", "bfloat16", static=True) == "bfloat16"
    assert auto.resolved_vision_dtype("cuda:1", "bfloat16", static=True) == "bfloat16"
    assert auto.resolved_vision_dtype("cuda", "bfloat16", static=False) == "float32"  # LeRobot's sampler: never cast
    assert auto.resolved_vision_dtype("cuda", "float32", static=True) == "float32"
    assert auto.resolved_vision_dtype("cpu", "bfloat16", static=True) == "float32"
    assert auto.resolved_vision_dtype("cuda", None, static=True) == "float32"  # SmolVLA: no dtype option
    assert EngineOptions(vision_dtype="float32").resolved_vision_dtype("cuda", "bfloat16", static=True) == "float32"
    assert EngineOptions(vision_dtype="bfloat16").resolved_vision_dtype("cpu", "float32", static=True) == "bfloat16"


def test_profile_gives_every_batch_size_the_time_of_its_bucket(engines):
    _, static = engines
    profile = static.profile(8, warmup=0, reps=1, log_progress=False)
    ms = profile.latency_ms
    assert len(ms) == 8 and ms[2] == ms[3] and ms[4] == ms[5] == ms[6] == ms[7]
    assert profile.name == "profiled:pi05+rtc"


class _ReplayOnCPU:
    """Stands in for a recorded CUDA graph on the CPU: ``replay`` recomputes the output from the
    recorded input buffers, as a replay does (the copy-in / padding / copy-out logic is tested)."""

    def __init__(self, sample, inputs, output) -> None:
        self.sample, self.inputs, self.output, self.replays = sample, inputs, output, 0

    def replay(self) -> None:
        self.replays += 1
        self.output.copy_(self.sample(self.inputs))


def test_a_recorded_bucket_is_fed_through_its_buffers_and_its_output_copied_out(engines):
    """A batch of 3 replays bucket 4's graph: the real rows are copied into the recorded buffers,
    the padding row repeats the last real row, the output returned is the real rows' and stays
    valid after the next replay. Inputs that do not fit the buffers run eagerly."""
    import torch

    from lerobot_armory.engine import cuda_graphs

    _, static = engines
    runner = BucketedSampler(static.sampler.sample)
    runner.set_buckets((4,))
    make = lambda b, s: static._sampler_inputs(  # noqa: E731
        static.preprocessor({**static.to_batch(batch(b, s)[0]), "task": batch(b, s)[1]}),
        {"noise": static._noise(batch(b, s)[2]), **rtc.guidance_kwargs(batch(b, s)[3], static.chunk_size, 8, "cpu")},
        static.config.tokenizer_max_length,  # one prompt length, as recorded
    )
    with torch.inference_mode():
        first = make(4, 0)
        buffers = [t.clone() for t in first.tensors()]
        output = static.sampler.sample(first.with_tensors(buffers))
        fake = _ReplayOnCPU(static.sampler.sample, first.with_tensors(buffers), output)
        runner.graphs[(4, first.prompt_length)] = cuda_graphs._Graph(fake, buffers, output)
        three = make(3, 5)
        got = runner(three)
        assert fake.replays == 1 and got.shape[0] == 3
        assert all(torch.equal(buf[3], buf[2]) for buf in buffers)  # padding repeats the last real row
        kept = got.clone()
        runner(make(4, 7))
        assert torch.equal(got, kept)  # a copy, not a view of the graph's output
        assert torch.equal(kept, static.sampler.sample(three.padded(4))[:3])
        # A prompt one token shorter than recorded (tokens and mask): served eagerly, not replayed.
        odd = three.with_tensors([t[:, :-1] if t.dim() == 2 else t for t in three.tensors()])
        assert runner.unrecorded == 0
        assert torch.equal(runner(odd), static.sampler.sample(odd.padded(4))[:3])
        assert fake.replays == 2 and runner.unrecorded == 1  # counted: armory_batches_unrecorded
        five = make(5, 3)  # larger than every bucket: eager at its own size, counted once
        assert torch.equal(runner(five), static.sampler.sample(five)) and runner.unrecorded == 2


def test_engine_options_are_checked_with_one_line_each(pi05_dir, demo_policy_dir):
    with pytest.raises(ConfigError, match="engine.cuda_graphs.*CUDA device"):
        PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(cuda_graphs="on"))
    with pytest.raises(ConfigError, match="engine.cuda_graphs.*one of"):
        PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(cuda_graphs="sometimes"))
    with pytest.raises(ConfigError, match="engine.attention"):
        PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(attention="flash"))
    with pytest.raises(ConfigError, match="engine.static_sampler.*act has no static sampler"):
        PolicyEngine(PolicyOptions(str(demo_policy_dir), "cpu"), engine=EngineOptions(static_sampler=True))
    auto = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"))  # auto on a CPU: LeRobot's sampler
    assert auto.sampler is None and "static" not in auto.description


def test_sdpa_attention_gives_the_same_chunks(engines, pi05_dir):
    lerobot, _ = engines
    sdpa = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(static_sampler=True, attention="sdpa"))
    obs, tasks, seeds, _ = batch(3)
    np.testing.assert_allclose(sdpa.infer(obs, tasks, seeds), lerobot.infer(obs, tasks, seeds), atol=1e-5)


def test_served_through_the_static_sampler_each_robots_chunks_equal_its_chunks_alone(pi05_dir):
    """A real server on the static sampler (no RTC, so a chunk is a function of its observation,
    prompt and noise alone; buckets 1 and 3, so a batch of two is padded) and prompt robots
    sharing batches."""
    static = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(static_sampler=True, graph_buckets="1,3,4"))
    static.warmup(3, log_progress=False)
    assert static.sampler.buckets == (1, 3)  # none above the cap
    server, robots = serve_prompt_robots(static, [TASKS[0], TASKS[1], TASKS[2]], max_batch_size=3)
    assert server.loop.stats.failed_batches == 0
    assert assert_shared_chunks_equal_alone(static, server, robots) >= 1


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_compiled_static_sampler_gives_the_same_chunks(pi05_dir, engines):
    """``--engine.compile_sampler=true``: inductor compiles the sampler's two layer functions (one
    bucket here: seconds on a 2-core CPU); its chunks equal LeRobot's to 1e-5."""
    lerobot, _ = engines
    compiled = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(static_sampler=True, compile_sampler=True, graph_buckets="2"))
    compiled.warmup(2, log_progress=False)
    assert compiled.sampler.buckets == (2,) and "compiled" in compiled.description
    obs, tasks, seeds, _ = batch(2, seed=3)
    np.testing.assert_allclose(compiled.infer(obs, tasks, seeds), lerobot.infer(obs, tasks, seeds), atol=1e-5)
    np.testing.assert_allclose(compiled.infer(obs[:1], tasks[:1], seeds[:1]), lerobot.infer(obs[:1], tasks[:1], seeds[:1]), atol=1e-5)
    with pytest.raises(ConfigError, match="engine.compile_sampler"):
        PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(compile_sampler=True))


def test_in_bf16_the_static_sampler_keeps_lerobots_weights_and_comes_nearer_a_float32_pi05(pi05_dir):
    """``--policy.dtype=bfloat16``: every weight stays in the dtype LeRobot loads it in (bf16 Gemma
    layers, float32 vision tower and action projections). LeRobot's order of operations keeps
    LeRobot's bf16 arithmetic (its chunks within a bf16 rounding of LeRobot's); the fused layers
    keep the residual stream in float32 and so give chunks at most 0.3× as far from the float32
    π0.5's as LeRobot's own bf16 chunks are (measured: 0.05×, on random weights whose small expert
    gates flatter it; benchmarks/bf16_accuracy.py measures undamped models)."""
    import torch

    bf16 = ["dtype=bfloat16"]
    float32 = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"))
    lerobot = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu", overrides=bf16))
    fused = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu", overrides=bf16), engine=EngineOptions(static_sampler=True))
    ordered = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu", overrides=bf16), engine=EngineOptions(static_sampler=True, fused_kernels=False))
    for engine in (fused, ordered):
        model = engine.policy.model
        assert model.paligemma_with_expert.gemma_expert.model.layers[0].self_attn.q_proj.weight.dtype == torch.bfloat16
        assert model.action_out_proj.weight.dtype == torch.float32
    assert fused.fused_kernels and not ordered.fused_kernels
    for b in (1, 3):
        obs, tasks, seeds, _ = batch(b)
        want, stock = float32.infer(obs, tasks, seeds), lerobot.infer(obs, tasks, seeds)
        np.testing.assert_allclose(ordered.infer(obs, tasks, seeds), stock, atol=1e-2)
        ours, theirs = np.abs(fused.infer(obs, tasks, seeds) - want).max(), np.abs(stock - want).max()
        assert ours <= 0.3 * theirs, (b, ours, theirs)


@pytest.mark.slow
@pytest.mark.subprocess
def test_the_server_command_refuses_graphs_without_a_gpu_in_one_line(pi05_dir):
    """``--engine.cuda_graphs=on`` (which the YAML-based parser reads as a boolean) on a CPU: exit 2
    with one line, before any robot could connect."""
    import subprocess
    import sys

    cmd = [sys.executable, "-m", "lerobot_armory.entrypoints.server", f"--policy.path={pi05_dir}", "--policy.device=cpu",
           "--engine.cuda_graphs=on", "--port=0"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1] == (
        "lerobot-armory-server: error: engine.cuda_graphs: on needs a CUDA device; this engine runs on cpu"
    )


@pytest.fixture(scope="module")
def two_camera_dir(tmp_path_factory):
    """A tiny π0.5 with two cameras (as LIBERO's: a view and a wrist)."""
    from lerobot_armory.demo.build import main

    path = tmp_path_factory.mktemp("pi05-2cam") / "pi05"
    main(["--kind=pi05", "--size=tiny", f"--output={path}", "--chunk_size=10", "--cameras=front,wrist", "--state_dim=3"])
    return path


def test_two_cameras_pass_the_vision_tower_as_one_batch_with_the_same_chunks(two_camera_dir):
    """With two cameras the static sampler runs SigLIP once on both (LeRobot runs it per camera):
    the chunks still equal LeRobot's, unpadded and padded."""
    path = two_camera_dir
    lerobot = PolicyEngine(PolicyOptions(str(path), "cpu"))
    static = PolicyEngine(PolicyOptions(str(path), "cpu"), engine=EngineOptions(static_sampler=True))
    static.warmup(4, log_progress=False)
    assert len(static.config.image_features) == 2
    for b in (1, 3):
        obs = [static.example_observation(seed=10 + k) for k in range(b)]
        tasks, seeds = [TASKS[k % 3] for k in range(b)], list(range(b))
        np.testing.assert_allclose(static.infer(obs, tasks, seeds), lerobot.infer(obs, tasks, seeds), atol=1e-5)


def test_a_failed_graph_recording_serves_unrecorded_with_auto_and_is_refused_with_on(pi05_dir, monkeypatch, caplog):
    """A recording that fails on the device (simulated: the CPU cannot record) does not take the
    server down with ``auto``: the static sampler serves the same chunks unrecorded and says why;
    with ``on`` start-up stops with one line."""
    import logging

    def broken(self, example, warmup=3):
        raise RuntimeError("operation not permitted when stream is capturing\nmore lines")

    monkeypatch.setattr(BucketedSampler, "capture", broken)
    engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(static_sampler=True))
    engine.graphs_wanted = True  # as on a CUDA device with --engine.cuda_graphs=auto
    with caplog.at_level(logging.WARNING):
        engine.warmup(2, log_progress=False)
    assert not engine.sampler.captured and not engine.graphs_wanted
    assert "recording the CUDA graph of bucket 2 failed: RuntimeError: operation not permitted" in engine.description
    assert any("serving with the static sampler unrecorded" in r.message for r in caplog.records)
    obs, tasks, seeds, _ = batch(2)
    assert engine.infer(obs, tasks, seeds).shape == (2, 10, 2)
    refused = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(static_sampler=True))
    refused.graphs_wanted, refused.engine_options.cuda_graphs = True, "on"
    with pytest.raises(ConfigError, match="engine.cuda_graphs: recording the CUDA graph of bucket 2 failed"):
        refused.warmup(2, log_progress=False)


def test_a_hostile_row_changes_nothing_for_its_batch_mates(engines):
    """One robot with a non-finite state, saturated images and the longest hostile prompt, batched
    (and padded to bucket 4) with two honest robots: the honest rows are their chunks alone (1e-5;
    bit for bit on the development CPU), and the hostile row does not fail the batch."""
    from lerobot_armory.entrypoints.grpc.service import MAX_TASK

    _, static = engines
    obs, tasks, seeds, _ = batch(3, seed=11)
    bad = {k: v.copy() for k, v in obs[0].items()}
    bad["observation.state"][:] = [np.inf, np.nan]
    bad["observation.images.front"][:] = 255
    hostile = ("Task: \x00\x1b[2J;\nAction: 🤖" + "ünïcødé\u202e" * 400)[:MAX_TASK]
    together = static.infer([bad, obs[1], obs[2]], [hostile, tasks[1], tasks[2]], seeds)
    for k in (1, 2):
        np.testing.assert_allclose(together[k], static.infer([obs[k]], [tasks[k]], [seeds[k]])[0], atol=1e-5, rtol=0)


def test_creating_parameters_on_a_device_that_fails_falls_back_to_the_cpu(pi05_dir, caplog):
    """π0.5's parameters are created on the CUDA device when the engine serves there (minutes of
    CPU initialisation saved for the full size); where that fails — here: no CUDA at all — the
    policy loads the usual way, with a warning, never a failed start."""
    import logging

    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy

    from lerobot_armory.engine import loading

    config = PreTrainedConfig.from_pretrained(str(pi05_dir))
    config.device = "cpu"
    with caplog.at_level(logging.WARNING):
        policy = loading.from_pretrained(PI05Policy, str(pi05_dir), config, "cuda")
    assert next(policy.parameters()).device.type == "cpu"
    assert any("creating pi05's parameters on cuda failed" in r.message for r in caplog.records)


def test_lerobots_own_order_of_operations_stays_one_option_away(engines, pi05_dir):
    """``--engine.fused_kernels=false`` runs LeRobot's sequence of operations (the reference the
    fused kernels are held to); both equal LeRobot's chunks (1e-5), unguided and guided."""
    lerobot, fused = engines
    plain = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), RTC, EngineOptions(static_sampler=True, fused_kernels=False, graph_buckets="1,4"))
    plain.warmup(4, log_progress=False)
    assert fused.fused_kernels and "fused kernels" in fused.description
    assert not plain.fused_kernels and "fused kernels" not in plain.description
    for b in (1, 3):
        obs, tasks, seeds, prefixes = batch(b, seed=5)
        want = lerobot.infer(obs, tasks, seeds)
        np.testing.assert_allclose(plain.infer(obs, tasks, seeds), want, atol=1e-5, rtol=0)
        np.testing.assert_allclose(fused.infer(obs, tasks, seeds), want, atol=1e-5, rtol=0)
        np.testing.assert_allclose(
            plain.infer_guided(obs, tasks, seeds, prefixes)[1], lerobot.infer_guided(obs, tasks, seeds, prefixes)[1], atol=1e-5, rtol=0
        )


def test_fusing_keeps_every_weight_and_adds_no_memory(pi05_dir):
    """The fused projections are the layers' own weights: after fusing, every parameter has the
    value it had, q/k/v (and gate/up) of a layer are views of one tensor, the parameters occupy
    the bytes they did, and a second sampler over the same policy shares the first's tensors."""
    import torch

    from lerobot_armory.acceleration.pi05_static import StaticPi05

    engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"))  # LeRobot's sampler: nothing fused yet
    policy = engine.policy
    before = {k: v.detach().clone() for k, v in policy.state_dict().items()}

    def parameter_bytes() -> int:
        return sum({p.untyped_storage().data_ptr(): p.untyped_storage().nbytes() for p in policy.parameters()}.values())

    bytes_before = parameter_bytes()
    first = StaticPi05(policy)
    assert first.fused and first.unfused_reason is None
    after = policy.state_dict()
    assert before.keys() == after.keys() and all(torch.equal(before[k], after[k]) for k in before)
    assert parameter_bytes() == bytes_before
    for layer in (*first.vlm.layers, *first.expert.layers):
        attn, mlp = layer.self_attn, layer.mlp
        qkv, gate_up = first.ops.qkv_weight(attn), first.ops.gate_up_weight(mlp)
        assert qkv.data_ptr() == attn.q_proj.weight.data_ptr() and gate_up.data_ptr() == mlp.gate_proj.weight.data_ptr()
        assert torch.equal(qkv, torch.cat([attn.q_proj.weight, attn.k_proj.weight, attn.v_proj.weight]))
        assert torch.equal(gate_up, torch.cat([mlp.gate_proj.weight, mlp.up_proj.weight]))
    second = StaticPi05(policy)
    attn = first.expert.layers[0].self_attn
    assert second.ops.qkv_weight(attn).data_ptr() == first.ops.qkv_weight(attn).data_ptr()
    assert parameter_bytes() == bytes_before


def test_fused_kernels_halve_the_launches_of_a_sample(engines, pi05_dir):
    """Counted as a GPU would launch them (``OpTrace`` under no_grad: composite ops decomposed,
    ``rms_norm`` one kernel where CUDA has it): the fused sampler launches at most 0.6× the
    kernels of LeRobot's order at every bucket, and neither waits for the host."""
    import torch

    from lerobot_armory.acceleration.op_trace import OpTrace
    from lerobot_armory.acceleration.pi05_static import StaticPi05

    _, static = engines
    plain = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), RTC)
    samplers = {"plain": StaticPi05(plain.policy, guided=True, fused=False), "fused": StaticPi05(static.policy, guided=True)}
    for b in BUCKETS:
        obs, tasks, seeds, prefixes = batch(b)
        kwargs = {"noise": static._noise(seeds), **rtc.guidance_kwargs(prefixes, static.chunk_size, RTC.execution_horizon, "cpu")}
        inputs = static._sampler_inputs(static.preprocessor({**static.to_batch(obs), "task": tasks}), kwargs)
        launches = {}
        for name, sampler in samplers.items():
            with torch.no_grad():
                sampler.sample(inputs)  # the per-size constants, outside the count
                with OpTrace() as trace:
                    sampler.sample(inputs)
            assert not trace.host_syncs, (name, dict(trace.host_syncs))
            launches[name] = trace.launches
        assert launches["fused"] <= 0.6 * launches["plain"], launches


def test_fused_keys_and_values_leave_the_rotation_straight_into_the_cache(engines):
    """The fused rotary table leaves v's rows as they are (cos 1, sin 0: bit for bit), so keys and
    values come out of one rotation side by side, and its last kernel stores them straight into
    the cache behind what is there (LeRobot's order: a copy of k and one of v per layer pass), with
    the same chunks."""
    import torch

    from lerobot_armory.acceleration.op_trace import OpTrace
    from lerobot_armory.acceleration.pi05_static import StaticPi05

    _, static = engines
    fused, plain = StaticPi05(static.policy, guided=True), StaticPi05(static.policy, guided=True, fused=False)
    attn = fused.expert.layers[0].self_attn
    x = torch.randn(2, 5, attn.q_proj.in_features, generator=torch.Generator().manual_seed(3))
    positions = torch.arange(5)[None].expand(2, 5) + 7
    caches = {"plain": plain.ops.new_cache(attn, x, 3, 6), "fused": fused.ops.new_cache(attn, x, 3, 6)}
    caches["plain"][0].fill_(7.0), caches["plain"][1].fill_(7.0), caches["fused"].fill_(7.0)
    with torch.no_grad():
        q_plain = plain.ops.qkv(attn, x, plain.ops.rope(plain.expert, x, positions), caches["plain"], 3)
        with OpTrace() as trace:
            q_fused = fused.ops.qkv(attn, x, fused.ops.rope(fused.expert, x, positions), caches["fused"], 3)
    assert "aten.copy_.default" not in trace.launched
    (k, v), kv = caches["plain"], caches["fused"]
    assert kv.shape == (2, fused.ops.cache_length(3, 6), 2, attn.head_dim) and k.shape[2] == 9
    assert torch.equal(kv[:, 3:8, 1], v[:, 0, 3:8])
    assert torch.allclose(kv[:, 3:8, 0], k[:, 0, 3:8], atol=1e-6, rtol=0)
    assert (kv[:, :3] == 7).all() and (kv[:, 8:] == 7).all()  # nothing written outside positions 3..7
    assert q_fused.is_contiguous()
    torch.testing.assert_close(q_fused, q_plain.transpose(1, 2) * attn.scaling, atol=1e-6, rtol=0)

    obs, tasks, seeds, prefixes = batch(3, seed=5)
    kwargs = {"noise": static._noise(seeds), **rtc.guidance_kwargs(prefixes, static.chunk_size, RTC.execution_horizon, "cpu")}
    inputs = static._sampler_inputs(static.preprocessor({**static.to_batch(obs), "task": tasks}), kwargs)
    passes = len(fused.vlm.layers) + fused.num_steps * len(fused.expert.layers)
    chunks = {}
    for name, s, copies in (("fused", fused, 0), ("plain", plain, 2 * passes)):
        with torch.no_grad():
            s.sample(inputs)  # the per-size constants, outside the count
            with OpTrace() as trace:
                chunks[name] = s.sample(inputs)
        assert trace.launched.get("aten.copy_.default", 0) == copies, (name, trace.launched.get("aten.copy_.default"), passes)
    torch.testing.assert_close(chunks["fused"], chunks["plain"], atol=1e-5, rtol=0)


def test_a_layer_that_cannot_be_fused_is_served_in_lerobots_order_and_says_why(pi05_dir, caplog):
    """A checkpoint whose K projection has a bias (π0.5's has none) cannot share one q/k/v weight:
    the static sampler runs LeRobot's order, the log says why, and the chunks still equal LeRobot's
    on that same checkpoint (its bias applied)."""
    import logging

    import torch

    engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"))
    k_proj = engine.policy.model.paligemma_with_expert.gemma_expert.model.layers[1].self_attn.k_proj
    k_proj.bias = torch.nn.Parameter(torch.linspace(-0.5, 0.5, k_proj.out_features))
    obs, tasks, seeds, _ = batch(2, seed=7)
    want = engine.infer(obs, tasks, seeds)
    with caplog.at_level(logging.INFO):
        engine.use_sampler(EngineOptions(static_sampler=True))
    assert engine.sampler is not None and not engine.fused_kernels
    assert any("fused kernels off): a projection has a bias" in r.message for r in caplog.records)
    np.testing.assert_allclose(engine.infer(obs, tasks, seeds), want, atol=1e-5, rtol=0)


def test_prompt_buckets_are_parsed_against_the_policys_prompt_length():
    from lerobot_armory.engine.cuda_graphs import parse_prompt_buckets

    assert parse_prompt_buckets("auto", 200) == (64, 128, 200)
    assert parse_prompt_buckets("auto", 100) == (64, 100)
    assert parse_prompt_buckets("auto", 64) == (16, 32, 64)  # a short prompt (π0's, SmolVLA's 48): 16 and 32
    assert parse_prompt_buckets("auto", 48) == (16, 32, 48)
    assert parse_prompt_buckets("auto", 16) == ()  # nothing below the full length: nothing to cut
    assert parse_prompt_buckets("off", 200) == ()
    assert parse_prompt_buckets("32, 16", 64) == (16, 32, 64)
    for bad in ("0,16", "100", "sixteen"):
        with pytest.raises(ConfigError, match="engine.prompt_buckets"):
            parse_prompt_buckets(bad, 64)


def test_prompts_cut_to_their_bucket_give_lerobots_chunks_and_the_profile_plans_for_the_longest(engines, pi05_dir):
    """The tiny π0.5 pads prompts to 64 tokens; with prompt buckets 16 and 32 a batch of short
    prompts runs at 16 or 32 columns (masked padding dropped) and its chunks still equal LeRobot's
    (1e-5), unguided and guided. ``d_infer`` is profiled at the full 64: the scheduler plans for the
    longest prompt a robot may send."""
    import torch

    lerobot, _ = engines
    cut = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), RTC, EngineOptions(static_sampler=True, prompt_buckets="16,32", graph_buckets="1,4"))
    assert cut.prompt_buckets == (16, 32, 64) and "prompts cut to 16,32,64 tokens" in cut.description
    seen: list[int] = []
    sample = cut.sampler.sample
    cut.sampler.sample = lambda inputs: (seen.append(inputs.prompt_length), sample(inputs))[1]
    cut.warmup(4, log_progress=False)
    for b in (1, 3):
        obs, tasks, seeds, prefixes = batch(b, seed=9)
        processed = cut.preprocessor({**cut.to_batch(obs), "task": tasks})
        used = int(processed["observation.language.attention_mask"].sum(dim=1).max())
        with torch.inference_mode():
            want_length = next(n for n in (16, 32, 64) if n >= used)
            assert cut._sampler_inputs(processed, {"noise": cut._noise(seeds)}).prompt_length == want_length < 64
        seen.clear()
        np.testing.assert_allclose(cut.infer(obs, tasks, seeds), lerobot.infer(obs, tasks, seeds), atol=1e-5, rtol=0)
        assert seen == [want_length]
        np.testing.assert_allclose(
            cut.infer_guided(obs, tasks, seeds, prefixes)[1], lerobot.infer_guided(obs, tasks, seeds, prefixes)[1], atol=1e-5, rtol=0
        )
    seen.clear()
    cut.profile(4, warmup=0, reps=1, log_progress=False)
    assert seen and set(seen) == {64}


def test_each_bucket_records_one_graph_per_prompt_length_longest_first(pi05_dir, monkeypatch):
    """Recording (faked: the CPU cannot record) covers every (batch bucket, prompt bucket), the
    longest prompt first in each bucket, with inputs of exactly that many prompt columns."""
    recorded: list[tuple[int, int]] = []

    def fake(self, example, warmup=3):
        recorded.append((example.rows, example.prompt_length))
        assert example.tokens.shape[1] == example.masks.shape[1] == example.prompt_length
        return 0.5

    monkeypatch.setattr(BucketedSampler, "capture", fake)
    engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(static_sampler=True, prompt_buckets="16,32", graph_buckets="1,2"))
    engine.graphs_wanted = True  # as on a CUDA device
    engine.warmup(2, log_progress=False)
    assert recorded == [(2, 64), (2, 32), (2, 16), (1, 64), (1, 32), (1, 16)]


def test_a_robot_with_the_longest_prompt_costs_its_batch_mates_no_chunk_change(engines, pi05_dir):
    """A hostile robot sends the longest prompt the wire allows: its batch runs at the full prompt
    length (no bucket below holds it), and its honest batch mates, which alone run cut to 16 or 32
    columns, get the same chunks (1e-5): cutting drops masked padding only."""
    from lerobot_armory.entrypoints.grpc.service import MAX_TASK

    cut = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(static_sampler=True, prompt_buckets="16,32", graph_buckets="1,3"))
    cut.warmup(3, log_progress=False)
    obs, tasks, seeds, _ = batch(3, seed=13)
    hostile = ("Task: \x00\x1b[2J;\nAction: " + "ünïcødé\u202e" * 400)[:MAX_TASK]
    together = cut.infer(obs, [hostile, tasks[1], tasks[2]], seeds)
    for k in (1, 2):
        np.testing.assert_allclose(together[k], cut.infer([obs[k]], [tasks[k]], [seeds[k]])[0], atol=1e-5, rtol=0)


def test_in_bf16_fused_norms_read_the_float32_stream_and_attention_skips_lerobots_float32_round_trips(pi05_dir):
    """bf16: the fused layers' residual stream is float32, so a norm reads it as it is and rounds
    once, as it hands the projections their bf16 input; the adaptive norm's scale is the norm's
    weight and its shift the next projection's bias (``W(n·s + t) = W(n·s) + W·t``): one norm
    kernel and one cast where LeRobot casts, norms, scales and casts again. Attention keeps mask,
    scores and softmax in bf16 (LeRobot's float32 mask makes them float32, then casts back): no
    cast inside the fused attention, its output LeRobot's within a bf16 rounding."""
    import torch
    from lerobot.utils.constants import OPENPI_ATTENTION_MASK_VALUE

    from lerobot_armory.acceleration.op_trace import OpTrace
    from lerobot_armory.acceleration.pi05_kernels import LeRobotOrder, Modulation
    from lerobot_armory.acceleration.pi05_static import StaticPi05

    engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu", overrides=["dtype=bfloat16"]))
    sampler = StaticPi05(engine.policy)
    ops, layer = sampler.ops, sampler.expert.layers[0]
    assert sampler.fused and layer.self_attn.q_proj.weight.dtype == torch.bfloat16
    gen = torch.Generator().manual_seed(0)
    width = layer.self_attn.q_proj.in_features
    h = ops.stream((3 * torch.randn(2, 5, width, generator=gen)).to(torch.bfloat16), torch.bfloat16)
    assert h.dtype == torch.float32
    scale1, shift = 1 + torch.randn(1, 1, width, generator=gen), torch.randn(1, 1, width, generator=gen)
    norm = layer.input_layernorm
    mod = ops.fold(Modulation(scale1, shift, torch.ones(1, 1, width, dtype=torch.bfloat16)), layer.self_attn)
    with torch.no_grad(), OpTrace() as trace:
        normed = ops.ada_norm(norm, h, mod)
    want = (torch.nn.functional.rms_norm(h, (width,), None, norm.eps) * scale1).to(torch.bfloat16)
    assert normed.dtype == torch.bfloat16 and trace.launches == 2  # the norm (its weight the scale), the cast
    torch.testing.assert_close(normed, want, atol=0, rtol=2**-8)  # one bf16 rounding apart at most
    assert mod.shift is None and mod.bias is not None
    qkv_weight = ops.qkv_weight(layer.self_attn).float()
    unfolded = torch.nn.functional.linear(torch.nn.functional.rms_norm(h, (width,), None, norm.eps) * scale1 + shift, qkv_weight)
    folded = torch.nn.functional.linear(normed.float(), qkv_weight) + mod.bias.float()
    torch.testing.assert_close(folded, unfolded, atol=0.02, rtol=0)  # bf16 roundings of the input and the bias (the shift's part: ~1)

    heads, d = layer.self_attn.config.num_attention_heads, layer.self_attn.head_dim
    q = torch.randn(2, 5, heads, d, generator=gen).to(torch.bfloat16)
    k, v = (torch.randn(2, 1, 9, d, generator=gen).to(torch.bfloat16) for _ in range(2))
    valid = torch.rand(2, 5, 9, generator=gen) > 0.4
    valid[..., 0] = True  # every query attends something
    additive = torch.where(valid, 0.0, float(OPENPI_ATTENTION_MASK_VALUE))
    mask = ops.mask(additive, torch.bfloat16)
    assert mask.dtype == torch.bfloat16
    scaling = layer.self_attn.scaling
    kv = torch.cat([k, v], dim=1).transpose(1, 2)  # the fused layout: (B, L, k's head and v's, d)
    with torch.no_grad(), OpTrace() as trace:
        out = ops.attend(layer.self_attn, q * scaling, kv, mask)  # Fused takes q scaled (its rotary table does it)
    assert "aten._to_copy.default" not in trace.launched and out.dtype == torch.bfloat16
    reference = LeRobotOrder("eager")
    want = reference.attend(layer.self_attn, q.transpose(1, 2), (k, v), reference.mask(additive, torch.bfloat16))
    torch.testing.assert_close(out, want, atol=1e-2, rtol=1e-2)


@pytest.mark.slow
def test_a_compiled_sampler_compiles_once_for_every_bucket_and_prompt_length_at_warm_up(two_camera_dir, monkeypatch, caplog):
    """``--engine.compile_sampler=true`` compiles the sampler's two layer functions (a VLM layer, an
    expert layer) with their batch and prompt dimensions dynamic: one compilation each at warm-up
    serves buckets 2 and 4 at all three prompt lengths (bucket 1 would be one more each: dynamo
    specialises a size of 1), said up front, none left for the first robots. Two cameras, as π0.5
    on LIBERO has. Dynamo's ``eager`` backend stands in for inductor here: the same tracing and
    guards, without the code generation."""
    import logging

    import torch
    from torch._dynamo.utils import counters

    real_compile = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: real_compile(fn, **{**kw, "backend": "eager"}))
    torch._dynamo.reset()
    counters.clear()
    options = EngineOptions(static_sampler=True, compile_sampler=True, graph_buckets="2,4", prompt_buckets="16,32")
    engine = PolicyEngine(PolicyOptions(str(two_camera_dir), "cpu"), engine=options)
    with caplog.at_level(logging.INFO, logger="lerobot_armory"):
        engine.warmup(4, log_progress=True)
        engine.profile(4, log_progress=False)
    assert "2 compilation(s)" in caplog.text and "then 6 shapes run once (2 batch buckets x 3 prompt lengths)" in caplog.text
    compiled = counters["stats"]["unique_graphs"]
    assert compiled == 2  # the VLM layer's and the expert layer's
    for b in (1, 2, 3):  # batches that fill their bucket and batches padded to it
        for words in (0, 12):  # prompts in different prompt buckets
            obs = [engine.example_observation(seed=k) for k in range(b)]
            engine.infer(obs, [TASKS[k % 3] + " please" * words for k in range(b)], list(range(b)))
    assert counters["stats"]["unique_graphs"] == compiled  # nothing compiled under robots
    torch._dynamo.reset()


@pytest.mark.slow
def test_a_compiled_engine_dropped_leaves_the_next_one_compiling(pi05_dir, two_camera_dir, monkeypatch):
    """Without a CUDA device, torch's tracing registered a no-op CUDA guard in the storage of the
    thread that first traced (an engine's device thread): once that engine was dropped, the next
    engine's compilation crashed the process (a segmentation fault). The sampler registers it on
    the thread that builds it. Two engines, the first dropped before the second compiles."""
    import gc

    import torch

    real_compile = torch.compile
    monkeypatch.setattr(torch, "compile", lambda fn, **kw: real_compile(fn, **{**kw, "backend": "eager"}))
    for path in (pi05_dir, two_camera_dir):  # the second reuses the code the first compiled where its guards allow
        engine = PolicyEngine(PolicyOptions(str(path), "cpu"), engine=EngineOptions(static_sampler=True, compile_sampler=True, graph_buckets="2"))
        engine.warmup(2, log_progress=False)
        obs = [engine.example_observation(seed=k) for k in range(2)]
        want = PolicyEngine(PolicyOptions(str(path), "cpu"), engine=EngineOptions(static_sampler=True)).infer(obs, TASKS[:2], [0, 1])
        np.testing.assert_allclose(engine.infer(obs, TASKS[:2], [0, 1]), want, atol=1e-5, rtol=0)
        del engine
        gc.collect()
    torch._dynamo.reset()


def test_a_vision_cast_that_runs_out_of_memory_leaves_every_weight_as_it_was(pi05_dir, monkeypatch):
    """``--engine.vision_dtype=bfloat16`` on a loaded engine (``use_sampler``) that runs out of
    memory halfway through the cast: the error reaches the caller, no weight of the tower or the
    projector has changed dtype or value, and the engine serves the same chunks as before."""
    import torch

    engine = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(static_sampler=True))
    model = engine.policy.model.paligemma_with_expert.paligemma.model
    before = {k: v.clone() for k, v in (*model.vision_tower.state_dict().items(), *model.multi_modal_projector.state_dict().items())}
    obs, tasks, seeds, _ = batch(2)
    want = engine.infer(obs, tasks, seeds)
    real_to, calls = torch.Tensor.to, []

    def to(self, *args, **kwargs):
        if torch.bfloat16 in args or kwargs.get("dtype") == torch.bfloat16:
            calls.append(1)
            if len(calls) == 5:
                raise torch.OutOfMemoryError("CUDA out of memory (simulated)")
        return real_to(self, *args, **kwargs)

    monkeypatch.setattr(torch.Tensor, "to", to)
    with pytest.raises(torch.OutOfMemoryError):
        engine.use_sampler(EngineOptions(static_sampler=True, vision_dtype="bfloat16"))
    monkeypatch.undo()
    assert len(calls) == 5
    after = {k: v for k, v in (*model.vision_tower.state_dict().items(), *model.multi_modal_projector.state_dict().items())}
    assert all(after[k].dtype == before[k].dtype and torch.equal(after[k], before[k]) for k in before)
    assert engine.vision_cast is None
    np.testing.assert_array_equal(engine.infer(obs, tasks, seeds), want)


def test_a_fitted_prompt_has_the_strides_of_a_recorded_batch_and_masks_what_it_adds():
    """A compiled sampler's guards check strides: a cut prompt must look like a padded or recorded
    batch (standard strides), also for one row, whose view is "contiguous" with the full row's
    stride. A prompt grown to a longer bucket keeps every column and adds masked ones."""
    import torch

    from lerobot_armory.acceleration.pi05_static import SamplerInputs

    for rows in (1, 3):
        tokens = torch.arange(1, rows * 48 + 1).view(rows, 48)
        inputs = SamplerInputs((torch.zeros(rows, 3, 4, 4),), tokens, torch.ones(rows, 48, dtype=torch.bool), torch.zeros(rows, 5, 2))
        cut = inputs.prompt_fitted(16)
        assert cut.tokens.stride() == cut.masks.stride() == (16, 1)
        assert torch.equal(cut.tokens, tokens[:, :16])
        grown = inputs.prompt_fitted(64)
        assert grown.prompt_length == 64 and grown.tokens.stride() == grown.masks.stride() == (64, 1)
        assert torch.equal(grown.tokens[:, :48], tokens) and torch.equal(grown.masks[:, :48], inputs.masks)
        assert not grown.masks[:, 48:].any() and not grown.tokens[:, 48:].any()
        assert inputs.prompt_fitted(48).prompt_length == 48
    with pytest.raises(ValueError, match="at least one column"):
        inputs.prompt_fitted(0)


def test_the_vision_tower_in_bf16_halves_its_memory_and_stays_near_float32(pi05_dir):
    """``--engine.vision_dtype=bfloat16``: the SigLIP tower and projector are cast once (half their
    bytes) and run in bf16; the chunks stay within bf16 rounding of the float32 tower's; the
    option needs the static sampler, and an engine whose tower was cast refuses to serve it
    otherwise (the float32 weights are gone)."""
    import torch

    _, tasks, seeds, _ = batch(2)
    obs = [observation(k, k) for k in range(2)]
    plain = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(static_sampler=True))
    vision = PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(static_sampler=True, vision_dtype="bfloat16"))

    def tower(engine: PolicyEngine) -> tuple[set, int]:
        model = engine.policy.model.paligemma_with_expert.paligemma.model
        params = [*model.vision_tower.parameters(), *model.multi_modal_projector.parameters()]
        return {p.dtype for p in params}, sum(p.numel() * p.element_size() for p in params)

    (dtypes, nbytes), (plain_dtypes, plain_bytes) = tower(vision), tower(plain)
    assert dtypes == {torch.bfloat16} and plain_dtypes == {torch.float32} and 2 * nbytes == plain_bytes
    assert "vision tower in bfloat16" in vision.description
    want, got = plain.infer(obs, tasks, seeds), vision.infer(obs, tasks, seeds)
    assert 0 < np.abs(got - want).max() < 5e-2
    with pytest.raises(ConfigError, match="engine.vision_dtype"):
        PolicyEngine(PolicyOptions(str(pi05_dir), "cpu"), engine=EngineOptions(vision_dtype="bfloat16"))
    with pytest.raises(ConfigError, match="engine.vision_dtype: must be one of"):
        EngineOptions(vision_dtype="float16").validate()
    served = vision.sampler
    with pytest.raises(ConfigError, match="loaded again"):
        vision.use_sampler(EngineOptions(static_sampler=False))
    # refused, the engine serves as it did: its sampler, options and chunks
    assert vision.sampler is served and vision.engine_options.vision_dtype == "bfloat16"
    np.testing.assert_array_equal(vision.infer(obs, tasks, seeds), got)
    with pytest.raises(ConfigError, match="engine.prompt_buckets"):  # refused before any weight is cast
        plain.use_sampler(EngineOptions(static_sampler=True, vision_dtype="bfloat16", prompt_buckets="9999"))
    assert plain.vision_cast is None and tower(plain)[0] == {torch.float32}


def test_the_fused_cache_is_a_multiple_of_8_positions_and_its_unwritten_positions_never_reach_a_chunk(engines):
    """The fused K/V cache rounds prefix + suffix up to a multiple of ``KEY_ALIGN`` positions (rows
    of scores 16 bytes apart: cuBLAS's fast Hopper kernels need it). The positions between prefix
    and suffix are never written: with every fresh allocation of the sampler filled with NaN (what
    a GPU's reused memory may hold), the chunks are the same, and the same as LeRobot's order,
    whose cache has no such positions."""
    from lerobot_armory.acceleration.pi05_kernels import KEY_ALIGN
    from lerobot_armory.acceleration.pi05_static import StaticPi05

    _, static = engines
    fused, plain = StaticPi05(static.policy, guided=True), StaticPi05(static.policy, guided=True, fused=False)
    inputs = sampler_inputs(static, 3, seed=6, horizon=RTC.execution_horizon)
    cameras = len(inputs.images)
    p = inputs.tokens.shape[1] + sum(emb.shape[1] for emb in fused.vision(inputs.images)[:cameras])
    length = fused.ops.cache_length(p, fused.suffix_length)
    assert length % KEY_ALIGN == 0 and length > p + fused.suffix_length, (p, fused.suffix_length)  # a gap to test
    assert plain.ops.cache_length(p, plain.suffix_length) == p + plain.suffix_length
    assert_unwritten_memory_never_reaches_a_chunk(fused, plain, inputs)


def test_the_vlms_mlp_hands_its_activation_contiguous_gate_and_up_and_the_chunks_stay_lerobots(engines):
    """Over the prefix's many rows the VLM's gate and up run as two products (``Fused``'s
    ``apart``), so the activation and the product after it read contiguous tensors (a GPU's
    vectorised elementwise kernels need them; one product's halves are strided); the expert keeps
    one product. The weights are the fused ones all the same, and the chunks stay LeRobot's."""
    import torch

    from lerobot_armory.acceleration.pi05_static import StaticPi05

    _, static = engines
    fused, plain = StaticPi05(static.policy, guided=True), StaticPi05(static.policy, guided=True, fused=False)
    seen: dict[str, list[bool]] = {"vlm": [], "expert": []}

    def recorder(name: str, act: torch.nn.Module) -> torch.nn.Module:
        class Recording(torch.nn.Module):
            def forward(self, gate: torch.Tensor) -> torch.Tensor:
                seen[name].append(gate.is_contiguous())
                return act(gate)

        return Recording()

    inputs = sampler_inputs(static, 3, seed=2, horizon=RTC.execution_horizon)
    saved = {mlp: mlp.act_fn for model in (fused.vlm, fused.expert) for mlp in (layer.mlp for layer in model.layers)}
    try:
        for name, model in (("vlm", fused.vlm), ("expert", fused.expert)):
            for layer in model.layers:
                layer.mlp.act_fn = recorder(name, saved[layer.mlp])
        with torch.no_grad():
            got = fused.sample(inputs)
    finally:
        for mlp, act in saved.items():
            mlp.act_fn = act
    last_vlm_mlp_unused = 1  # the last VLM layer's output is never read (its keys and values are)
    assert seen["vlm"] == [True] * (len(fused.vlm.layers) - last_vlm_mlp_unused)
    assert seen["expert"] and not any(seen["expert"])
    with torch.no_grad():
        torch.testing.assert_close(got, plain.sample(inputs), atol=1e-5, rtol=0)


@pytest.mark.parametrize("kind", ["pi05", "pi0"])
def test_with_float32_products_every_residual_sum_reads_one_dtype(kind, request, monkeypatch):
    """In bf16 on a GPU the fused sampler's output and down projections write float32 themselves
    (``torch.mm(out_dtype=float32)``, CUDA only): every residual sum then reads the float32 stream,
    a float32 product and (π0.5's expert) LeRobot's bf16 gate in float32, so none runs in PyTorch's
    mixed-dtype elementwise kernels, which a GPU does not vectorise. On the CPU it is off and says
    why; here the product is stood in for by its arithmetic (bf16 inputs, float32 sums and output,
    as cuBLAS computes it), called once for each sum, and the chunks stay as near a float32
    model's as with bf16 products. The product itself (meta tensors: shapes and dtypes) is float32."""
    import torch
    from torch.utils._python_dispatch import TorchDispatchMode

    from lerobot_armory.acceleration import pi05_kernels
    from lerobot_armory.acceleration.pi0_static import StaticPi0
    from lerobot_armory.acceleration.pi05_static import StaticPi05

    sampler = {"pi05": StaticPi05, "pi0": StaticPi0}[kind]
    path = str(request.getfixturevalue(f"{kind}_dir"))

    class ResidualDtypes(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.mixed = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
            if func in (torch.ops.aten.addcmul.default, torch.ops.aten.add.Tensor):
                self.mixed += len({a.dtype for a in args if isinstance(a, torch.Tensor)}) > 1
            return func(*args, **(kwargs or {}))

    meta = torch.empty(8, 16, dtype=torch.bfloat16, device="meta")
    assert pi05_kernels._float32_mm(meta, meta.t()).dtype == torch.float32
    float32 = PolicyEngine(PolicyOptions(path, "cpu"))
    bf16 = PolicyEngine(PolicyOptions(path, "cpu", overrides=["dtype=bfloat16"]), engine=EngineOptions(static_sampler=True))
    reference, off = sampler(float32.policy, fused=False), sampler(bf16.policy)
    assert not off.ops.float32_products and "CUDA only" in off.ops.float32_products_reason
    assert "float32" not in bf16.description.split("fused kernels")[1]
    calls = []

    def stand_in(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        assert a.dtype == b.dtype == torch.bfloat16
        calls.append(1)
        return torch.mm(a.float(), b.float())

    monkeypatch.setattr(pi05_kernels, "float32_products_reason", lambda device, dtype: None)
    monkeypatch.setattr(pi05_kernels, "_float32_mm", stand_in)
    on = sampler(bf16.policy)
    assert on.ops.float32_products
    for b in (1, 3):
        inputs = sampler_inputs(bf16, b, seed=b, guided=False)
        with torch.no_grad():
            want = reference.sample(inputs)
            with ResidualDtypes() as before:
                theirs = off.sample(inputs)
            calls.clear()
            with ResidualDtypes() as after:
                ours = on.sample(inputs)
        assert before.mixed > 0 and after.mixed == 0 and len(calls) == before.mixed, (before.mixed, after.mixed, len(calls))
        torch.testing.assert_close(ours, theirs, atol=1e-2, rtol=0)
        assert (ours - want).abs().max() <= 1.5 * (theirs - want).abs().max()
