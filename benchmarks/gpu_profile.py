"""GPU latency profile: ``d_infer(b)`` of ACT and π0.5, through the engine and bare, b = 1..8.

Configurations (``--configs``, any subset; each is loaded through ``--policy.path`` like a user's):

- ``act``: ACT with 2 cameras 224², dim 512, 4 encoder layers (≈ 41 M parameters, random weights);
- ``pi05-fp32`` / ``pi05-bf16``: π0.5 ``full`` (PaliGemma gemma_2b + expert gemma_300m, random
  weights, stand-in tokenizer, LIBERO-like inputs: two 224² cameras, 8-d state, chunk 50),
  ``--policy.dtype=float32|bfloat16``, LeRobot's own eager sampler (``--engine.cuda_graphs=off``);
- ``pi05-bf16-graphs``: the same policy served by our static sampler, one CUDA graph per bucket
  (``--engine.cuda_graphs=on``, buckets 1, 2, 4, 8); ``pi05-bf16-graphs-sdpa`` with
  ``--engine.attention=sdpa``; ``pi05-bf16-graphs-tf32`` with ``--engine.matmul_precision=high``
  (LeRobot keeps the SigLIP tower in float32 even in bf16: TF32 speeds its products);
  ``pi05-bf16-graphs-compiled`` with ``--engine.compile_sampler=true`` (and
  ``pi05-bf16-graphs-tf32-compiled``, today's default plus it); ``pi05-fp32-graphs`` in
  float32; a ``-ordered`` suffix (``pi05-bf16-graphs-ordered``, ``pi05-bf16-graphs-tf32-ordered``):
  ``--engine.fused_kernels=false``, LeRobot's sequence of operations in the static sampler (the
  graphs configurations fuse by default); a ``-fullprompt`` suffix: ``--engine.prompt_buckets=off``,
  every prompt at LeRobot's padded 200 tokens (by default the measured prompts, "pick up the block
  number k", are cut to 64); a ``-visionbf16`` suffix: ``--engine.vision_dtype=bfloat16``, the
  SigLIP tower and projector in bf16 (LeRobot keeps them in float32; cast in place, so the
  policy is loaded again for the configuration after it). Without it a graphed configuration
  names ``float32`` (the default before 2026-11-27 #8); the served default on a GPU is now
  ``pi05-bf16-graphs-tf32-visionbf16`` (``--engine.vision_dtype=auto``); a ``-latevision`` suffix:
  ``--engine.early_vision=false`` (one graph a bucket and prompt length, replayed after the
  pre-processor, where by default the vision tower's own graph starts before it); an ``-unaligned``
  suffix: the fused K/V caches prefix + suffix positions end to end (before 2026-11-28; by default
  rounded up to a multiple of 8 so that attention's rows suit cuBLAS's Hopper kernels); a
  ``-stridedmlp`` suffix: the VLM's MLP gate and up as the halves of one product (before
  2026-11-28 #10; by default two contiguous products, so that the activation and the product after
  it run in PyTorch's vectorised kernels; meaningful with ``-notriton`` only, the Triton
  activation reading one product's halves); a ``-mixedresidual`` suffix: the output and down
  projections in bf16 (before 2026-11-28 #10; by default on a GPU they write float32, so that the
  residual sums read one dtype); a ``-notriton`` suffix: PyTorch's operations where by default on a
  GPU two Triton kernels run the MLP's activation and each residual sum with the norm after it
  (before 2026-11-28 #10); all four (``-unaligned-stridedmlp-mixedresidual-notriton``): the
  sampler of 2026-11-27; a ``-notritonattention`` suffix: PyTorch's operations for the rotary
  embedding and attention's mask + softmax, which by default on a GPU two more Triton kernels run
  (before 2026-11-28 #11: that day's measured default); a ``-twopasssoftmax`` suffix: the Triton
  softmax in two passes over each row (before 2026-11-28 #12; by default one where the row fits);
- ``pi05-fp32-compiled`` / ``pi05-bf16-compiled``: LeRobot's ``--policy.compile_model=true``
  (``--compile_mode``; the engine keeps the compiled model only if it measured faster).
- ``pi0-bf16`` / ``pi0-bf16-graphs-tf32``: LeRobot's π0 ``full`` (the same PaliGemma and expert
  sizes, the state as a suffix token, a 48-token prompt, cut to 16 when graphed), LeRobot's eager sampler against our
  static π0 sampler (``acceleration/pi0_static.py``) recorded as graphs with TF32, the default.
- ``smolvla-fp32`` / ``smolvla-fp32-graphs-tf32`` / ``smolvla-fp32-graphs-tf32-ordered``: SmolVLA at
  SmolVLM2-500M's sizes (``--size`` full; 450 M parameters, float32 as LeRobot builds it from its
  configuration, 16 VLM layers and a 0.75-wide expert, 512² images), LeRobot's eager sampler
  against our static SmolVLA sampler (``acceleration/smolvla_static.py``) recorded as graphs with TF32,
  with its fused kernels and in LeRobot's order (``smolvla-fp32-graphs-tf32-unaligned``: fused, with
  LeRobot's prefix and cache lengths, as before 2026-11-28).

Configurations of one policy and dtype share one load (the full π0.5 takes minutes to load): the
policy is measured with each sampler in turn, in the same call, so the figures compare.

For each batch size: *engine* = ``PolicyEngine.infer`` on wire arrays (stacking, the uint8 upload,
pre-processor with the prompt's tokenizer, the forward pass, post-processor, the copy back) and
*bare* = ``PolicyEngine.forward`` alone on a batch already pre-processed on the device (the model's
own time: LeRobot's ``predict_action_chunk``, or the static sampler / its graph); both median of
``--reps`` after the engine's warm-up, synchronised. With graphs, the seconds to record each
bucket, the peak GPU memory, and how far its chunks are from LeRobot's eager sampler's on the
same inputs (b = 1, 3, 8; measured when the eager configuration of that dtype ran first in the
call) are written too (``--float32_reference``: and, for every bf16 configuration, from LeRobot's
eager sampler on the same weights in float32, loaded after the others), and (``--kernels``; run it in a call of its own: profiling graph replays has
faulted CUDA in some versions) where a pass's device time goes: one
pass at b = 1 and at the largest b traced with ``torch.profiler`` (the kernels inside a graph's
replay one by one), its kernel time summed by kind — matrix products, attention, norms, copies,
elementwise — with the 40 longest kernels; ``--stages``: each step of a served batch timed alone,
synchronised (what the engine adds to the bare pass). Results merge into ``docs/results/gpu/<device>.json``;
its top-level ``latency_ms`` is the fastest π0.5 bf16 configuration through the engine, so the
file loads as ``--latency_profile=FILE``. A figure is drawn beside the JAX reference's H100 table
(openpi in JAX, the π0.5 latencies reported in the real-time chunking paper).

Targets (π0.5 full, bf16, CUDA graphs, on an H100): b = 1 ≤ 25 ms, 2 ≤ 32, 3 ≤ 40, 4 ≤ 47,
5 ≤ 55, 8 ≤ 80 ms through the engine (each at most 0.65× the JAX reference), and all buckets
recorded in ≤ 60 s.

    python3 benchmarks/gpu_profile.py --configs=pi05-bf16,pi05-bf16-graphs --work_dir=/tmp/gp
    .venv/bin/python benchmarks/gpu_profile.py --allow_cpu --size=tiny --configs=pi05-bf16-graphs   # script check only

Exits 1 on a missed target, 2 without a GPU unless ``--allow_cpu`` (whose figures are CPU figures
and are never written under docs/results/gpu by default; on a CPU "graphs" run the static sampler
unrecorded).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import os
import platform
import re
import statistics
import sys
import traceback
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets  # noqa: E402

CONFIGS = (
    "act", "pi05-fp32", "pi05-bf16", "pi05-fp32-compiled", "pi05-bf16-compiled",
    "pi05-bf16-graphs", "pi05-bf16-graphs-sdpa", "pi05-bf16-graphs-tf32", "pi05-bf16-graphs-compiled", "pi05-fp32-graphs",
    "pi05-bf16-graphs-ordered", "pi05-bf16-graphs-tf32-ordered", "pi05-bf16-graphs-tf32-fullprompt",
    "pi05-bf16-graphs-tf32-ordered-fullprompt", "pi05-bf16-graphs-tf32-visionbf16", "pi05-bf16-graphs-tf32-compiled",
    "pi05-bf16-graphs-tf32-visionbf16-compiled", "pi05-bf16-graphs-tf32-visionbf16-latevision",
    "pi05-bf16-graphs-tf32-visionbf16-unaligned", "pi05-bf16-graphs-tf32-visionbf16-mixedresidual",
    "pi05-bf16-graphs-tf32-visionbf16-notriton", "pi05-bf16-graphs-tf32-visionbf16-stridedmlp-notriton",
    "pi05-bf16-graphs-tf32-visionbf16-unaligned-stridedmlp-mixedresidual-notriton",
    "pi05-bf16-graphs-tf32-visionbf16-notritonattention", "pi05-bf16-graphs-tf32-visionbf16-twopasssoftmax",
    "pi0-bf16", "pi0-bf16-graphs-tf32",
    "smolvla-fp32", "smolvla-fp32-graphs-tf32-ordered", "smolvla-fp32-graphs-tf32", "smolvla-fp32-graphs-tf32-unaligned",
)  # fmt: skip
# π0.5 in JAX (openpi) on an H100, ms at b = 1..5: the real-time chunking paper's latency table.
JAX_H100 = (42.3, 56.0, 66.1, 79.3, 87.2)
# Our targets for π0.5 bf16 with CUDA graphs on an H100, ms by batch size (≤ 0.65× JAX_H100).
GRAPH_TARGETS_H100 = {1: 25.0, 2: 32.0, 3: 40.0, 4: 47.0, 5: 55.0, 8: 80.0}
CAPTURE_TARGET_S = 60.0


def engine_options(config: str) -> Any:
    """The ``--engine.*`` options of a configuration."""
    from lerobot_armory.engine.options import EngineOptions

    # Precision named in every configuration: "auto" would turn TF32 on for bf16 on a GPU, and
    # LeRobot's eager sampler is measured as LeRobot runs it.
    flags = _flags(config)
    precision = "high" if "tf32" in flags else "highest"
    if "-graphs" not in config:
        return EngineOptions(cuda_graphs="off", matmul_precision=precision)
    return EngineOptions(
        cuda_graphs="on" if _cuda() else "off",  # on a CPU: the static sampler, unrecorded
        static_sampler=True,
        attention="sdpa" if "sdpa" in flags else "eager",
        fused_kernels="ordered" not in flags,
        # Compiled: the measured prompts are cut to 64 either way, so 64 and the full length are all
        # a compiled run records (fewer shapes to run at warm-up; its compilations are four, two
        # layer functions × bucket 1 and the others, whatever the prompt lengths).
        prompt_buckets="off" if "fullprompt" in flags else ("64" if "compiled" in flags else "auto"),
        compile_sampler="compiled" in flags,
        graph_buckets=ARGS.graph_buckets,
        matmul_precision=precision,
        vision_dtype="bfloat16" if "visionbf16" in flags else "float32",
        early_vision="latevision" not in flags,
    )


def _flags(config: str) -> set[str]:
    """The suffixes after ``-graphs`` (none for an eager configuration)."""
    return set(config.split("-graphs")[1].split("-")[1:]) if "-graphs" in config else set()


# Suffixes that undo one of the default's kernel choices (``as_before``): a configuration with one
# beside the same without says what the choice gives.
BEFORE = ("unaligned", "stridedmlp", "mixedresidual", "notriton", "notritonattention", "twopasssoftmax")


@contextlib.contextmanager
def as_before(config: str) -> Iterator[None]:
    """The same engine with some of its newer kernel choices undone, by suffix:

    - ``-unaligned``: the fused K/V caches (and SmolVLA's prefix) as long as LeRobot's, as before
      2026-11-28, where by default they are rounded up to ``KEY_ALIGN`` positions
      (``Fused.cache_length``, ``SmolVLAFused.prefix_length``);
    - ``-stridedmlp``: the VLM's MLP gate and up as the two halves of one product, as before
      2026-11-28 #10, where by default they are two contiguous products
      (``StaticPi05.vlm_mlp_apart``); only with ``-notriton``: the Triton activation kernel
      reads one product's halves either way;
    - ``-mixedresidual``: the output and down projections in bf16, so that each residual sum
      reads two dtypes, as before 2026-11-28 #10, where on a GPU they are written in float32
      (``pi05_kernels.float32_products_reason``);
    - ``-notriton``: PyTorch's operations for the MLP's activation and for each residual sum with
      the norm after it (attention's, and the MLP's with the next layer's input norm), as before
      2026-11-28 #10, where on a GPU two Triton kernels run them (``pi05_kernels.hand_kernels_reason``);
      with it every Triton kernel is off;
    - ``-notritonattention``: PyTorch's operations for the rotary embedding and for attention's
      mask and softmax, as before 2026-11-28 #11, where on a GPU a Triton kernel runs each
      (``Fused.triton_attention``); the MLP's and the norms' Triton kernels stay;
    - ``-twopasssoftmax``: the Triton softmax reading each row twice (two passes), as before
      2026-11-28 #12, where a row that fits its block is read once (``masked_softmax``'s
      ``one_pass``)."""
    from lerobot_armory.acceleration import pi05_kernels
    from lerobot_armory.acceleration.pi05_kernels import Fused, LeRobotOrder
    from lerobot_armory.acceleration.pi05_static import StaticPi05
    from lerobot_armory.acceleration.smolvla_kernels import SmolVLAFused, SmolVLAOrdered

    flags = _flags(config)
    patched: list[tuple[Any, str, Any]] = []  # (class or module, attribute, the value before)
    if "unaligned" in flags:
        patched += [(cls, name, lerobots.__dict__[name]) for cls, lerobots, name in (
            (Fused, LeRobotOrder, "cache_length"), (SmolVLAFused, SmolVLAOrdered, "cache_length"), (SmolVLAFused, SmolVLAOrdered, "prefix_length"))]  # fmt: skip
    if "stridedmlp" in flags:
        patched.append((StaticPi05, "vlm_mlp_apart", False))
    if "mixedresidual" in flags:
        patched.append((pi05_kernels, "float32_products_reason", lambda device, dtype: "-mixedresidual"))
    if "notriton" in flags:
        patched.append((pi05_kernels, "hand_kernels_reason", lambda *args: "-notriton"))
    if "notritonattention" in flags:
        patched.append((Fused, "triton_attention", False))
    if "twopasssoftmax" in flags:
        patched.append((pi05_kernels, "masked_softmax", functools.partial(pi05_kernels.masked_softmax, one_pass=False)))
    saved = [vars(owner)[name] for owner, name, _ in patched]  # a class's or a module's own
    for cls, name, before in patched:
        setattr(cls, name, before)
    try:
        yield
    finally:
        for (cls, name, _), now in zip(patched, saved, strict=True):
            setattr(cls, name, now)


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def build(config: str, size: str, work: Path, compile_mode: str) -> tuple[str, list[str]]:
    """The policy directory of a configuration (built once per run) and its ``--policy.*`` overrides."""
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

    if config == "act":
        path = work / "act"
        if not (path / "config.json").is_file():
            small = size == "tiny"
            make_demo_policy(
                DemoPolicyConfig(
                    output=str(path), kind="act", chunk_size=50, state_dim=14, cameras="top,wrist",
                    image_size=96 if small else 224, dim_model=128 if small else 512, n_encoder_layers=2 if small else 4,
                )
            )  # fmt: skip
        return str(path), []
    dtype = "bfloat16" if "bf16" in config else "float32"
    kind = policy_kind(config)
    # Saved in the dtype it is served in: a bf16 directory is half the bytes to write and load.
    path = work / f"{kind}-{size}-{dtype}"
    if not (path / "config.json").is_file():
        print(f"building {kind} {size} {dtype} (random weights) in {path} ...", flush=True)
        t0 = time.perf_counter()
        make_demo_policy(
            DemoPolicyConfig(
                output=str(path), kind=kind, size=size, chunk_size=50, state_dim=8, cameras="base,wrist", image_size=224, dtype=dtype,
                device="cuda" if _cuda() else "cpu",  # random weights created on the GPU: seconds, not minutes
            )
        )
        print(f"  built in {time.perf_counter() - t0:.0f} s", flush=True)
    overrides = [] if kind == "smolvla" else [f"dtype={dtype}"]  # SmolVLA's config has no dtype: float32 as built
    if config.endswith("compiled") and "-graphs" not in config:
        overrides += ["compile_model=true", f"compile_mode={compile_mode}"]
    return str(path), overrides


def policy_kind(config: str) -> str:
    """The LeRobot policy type a configuration serves (``pi05-…``, ``pi0-…``, ``smolvla-…``)."""
    return config.split("-")[0]


def reference_key(config: str, overrides: list[str]) -> str:
    """Which LeRobot eager run a configuration's chunks are compared with: the same policy type
    and dtype (one load)."""
    return f"{policy_kind(config)}:{overrides[0] if overrides else ''}"


def chunks(engine: Any, sizes: tuple[int, ...] = (1, 3, 8)) -> dict[int, Any]:
    """The chunks of fixed batches (observations, prompts, noise seeds) per batch size: the same
    inputs for every configuration of a call, so their chunks compare."""
    out = {}
    for b in sizes:
        obs = [engine.example_observation(seed=100 + k) for k in range(b)]
        out[b] = engine.infer(obs, [f"put the bowl on plate {k}" for k in range(b)], [7 + k for k in range(b)])
    return out


def agreement(reference: dict[int, Any], other: dict[int, Any]) -> dict[str, float]:
    """Largest |difference| between two configurations' chunks, and the chunks' largest |value|."""
    diff = max(float(abs(reference[b] - other[b]).max()) for b in reference)
    scale = max(float(abs(reference[b]).max()) for b in reference)
    return {"max_abs_diff": round(diff, 6), "max_abs_action": round(scale, 4)}


def measure(engine: Any, max_b: int, reps: int) -> tuple[list[float], list[float]]:
    """Median ms per batch size: through the engine, and bare (the forward pass alone)."""
    import torch

    def sync() -> None:
        if torch.cuda.is_available() and str(engine.device).startswith("cuda"):
            torch.cuda.synchronize(engine.device)

    engine_ms, bare_ms = [], []
    for b in range(1, max_b + 1):
        obs = [engine.example_observation(seed=k) for k in range(b)]
        tasks = [f"pick up the block number {k}" for k in range(b)]
        seeds = list(range(b))
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            engine.infer(obs, tasks, seeds)  # ends with the copy back to the host
            times.append((time.perf_counter() - t0) * 1000.0)
        engine_ms.append(statistics.median(times))
        bare_ms.append(statistics.median(engine.on_device(bare_forward, engine, obs, tasks, seeds, reps, sync)))
        print(f"    b={b}: engine {engine_ms[-1]:7.1f} ms   bare {bare_ms[-1]:7.1f} ms   ratio {bare_ms[-1] / engine_ms[-1]:.3f}", flush=True)
    return engine_ms, bare_ms


def bare_forward(engine: Any, obs: list, tasks: list[str], seeds: list[int], reps: int, sync: Any) -> list[float]:
    """ms of the forward pass alone on a batch already pre-processed on the device. Runs on
    the engine's device thread (via ``engine.on_device``), where the served forward passes run:
    a compiled model's CUDA graphs belong to that thread."""
    import torch

    times = []
    with torch.inference_mode():  # inputs made in the mode served batches are (a compiled sampler guards on it)
        batch = engine.to_batch(obs)
        batch["task"] = tasks
        kwargs = {"noise": engine._noise(seeds)} if engine.noise_shape is not None else {}
        ready = engine.preprocessor(batch)
        sync()
        for _ in range(reps):
            t0 = time.perf_counter()
            engine.forward(ready, kwargs)
            sync()
            times.append((time.perf_counter() - t0) * 1000.0)
    return times


def stage_breakdown(engine: Any, b: int, reps: int) -> dict[str, float]:
    """Median ms of each step of a served batch at size b, the device synchronised after each, so
    each step's figure is its host time plus the device work it queued: what the engine adds to
    the bare pass (stacking and upload, noise, the pre-processor with the tokenizer, the
    post-processor, the copy back) against the pass itself (``forward``: the prompt bucket's
    read-back, the copies into the graph's inputs, the replay). Runs on the device thread."""
    import torch

    cuda = str(engine.device).startswith("cuda")
    obs = [engine.example_observation(seed=k) for k in range(b)]
    tasks = [f"pick up the block number {k}" for k in range(b)]
    times: dict[str, list[float]] = {}

    def timed(name: str, fn: Any, *args: Any) -> Any:
        t0 = time.perf_counter()
        out = fn(*args)
        if cuda:
            torch.cuda.synchronize(engine.device)
        times.setdefault(name, []).append((time.perf_counter() - t0) * 1000.0)
        return out

    def run() -> None:
        with torch.inference_mode():
            for _ in range(reps + 1):  # the first is a warm-up, dropped below
                batch = timed("stack and upload", engine.to_batch, obs)
                batch["task"] = list(tasks)
                kwargs = timed("noise", lambda: {"noise": engine._noise(range(b))} if engine.noise_shape is not None else {})
                ready = timed("pre-processor", engine.preprocessor, batch)
                actions = timed("forward", engine.forward, ready, kwargs)
                actions = timed("post-processor", engine.postprocessor, actions)
                timed("copy back", lambda: actions.detach().to("cpu", torch.float32).numpy())

    engine.on_device(run)
    return {name: round(statistics.median(ms[1:]), 3) for name, ms in times.items()}


def add_stages(engine: Any, run: dict[str, Any]) -> None:
    """``run["stages_ms"]``: :func:`stage_breakdown` at b = 1 and the largest b (printed too)."""
    run["stages_ms"] = {str(b): stage_breakdown(engine, b, ARGS.reps) for b in sorted({1, ARGS.max_batch_size})}
    for b, stages in run["stages_ms"].items():
        print(f"  b={b} stages (ms): " + ", ".join(f"{k} {v:.2f}" for k, v in stages.items()), flush=True)


# Kernel names by what they do (first match wins): where a graphed batch's device time goes.
KERNEL_KINDS = (
    ("attention and softmax", r"flash|fmha|attention|sdpa|softmax"),  # first: flash kernels name cutlass types
    ("matrix products", r"gemm|gemv|cutlass|nvjet|xmma|cublas|(?<![a-z])mm(?![a-z])|addmm|bmm|matmul|conv"),
    ("norms", r"norm"),
    ("copies and casts", r"copy|memcpy|memset|cat|clone|contiguous|index"),
    ("elementwise", r"elementwise|vectorized|unrolled|reduce|mul|add|sub|div|silu|gelu|tanh|where|rsqrt|pow|mean|exp"),
)


LONGEST = 40  # kernels listed by name in a breakdown, longest first


def kernel_breakdown(engine: Any, b: int, reps: int = 3) -> dict[str, Any]:
    """Where one forward pass's device time goes at batch b: each kernel's time from
    ``torch.profiler`` (on a GPU, the kernels inside a CUDA graph replay are traced one by one),
    summed by kind (:data:`KERNEL_KINDS`), with the kernel count and the :data:`LONGEST` longest. On a CPU the
    same for aten ops' own CPU time (a script check, not a GPU figure)."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    cuda = str(engine.device).startswith("cuda")
    obs = [engine.example_observation(seed=k) for k in range(b)]
    batch = engine.to_batch(obs)
    batch["task"] = [f"pick up the block number {k}" for k in range(b)]

    def run() -> None:
        with torch.inference_mode():
            ready = engine.preprocessor(dict(batch))
            kwargs = {"noise": engine._noise(range(b))} if engine.noise_shape is not None else {}
            engine.forward(ready, kwargs)  # the prompt bucket's read-back happens here, before the graph
            if cuda:
                torch.cuda.synchronize(engine.device)
            with profile(activities=[ProfilerActivity.CUDA if cuda else ProfilerActivity.CPU]) as prof:
                for _ in range(reps):
                    engine.forward(ready, kwargs)
                if cuda:
                    torch.cuda.synchronize(engine.device)
        return prof

    prof = engine.on_device(run)
    rows = []
    for event in prof.key_averages():
        # Kernels have device time and the host's runtime calls none (and the reverse on a CPU).
        us = (getattr(event, "self_device_time_total", 0.0) or getattr(event, "self_cuda_time_total", 0.0)) if cuda else event.self_cpu_time_total
        if us > 0:
            rows.append((event.key, event.count / reps, us / 1000.0 / reps))
    kinds: dict[str, float] = {}
    for name, _, ms in rows:
        kind = next((k for k, pattern in KERNEL_KINDS if re.search(pattern, name, re.IGNORECASE)), "other")
        kinds[kind] = kinds.get(kind, 0.0) + ms
    rows.sort(key=lambda r: -r[2])
    return {
        "device_ms": round(sum(ms for _, _, ms in rows), 3),
        "kernels": round(sum(n for _, n, _ in rows)),
        "by_kind_ms": {k: round(v, 3) for k, v in sorted(kinds.items(), key=lambda kv: -kv[1])},
        # 40 and 300 characters: 10 and 120 (before 2026-11-28 #10) left 10.3 of 24.6 ms at b = 1
        # unnamed and cut an elementwise kernel's name before its functor (which operation it is).
        "longest": [{"name": name[:300], "per_pass": round(n, 1), "ms": round(ms, 3)} for name, n, ms in rows[:LONGEST]],
    }


def profile_config(
    engine: Any, config: str, overrides: list[str], device: str, reference: dict[str, dict[int, Any]], chunk_sets: dict[str, dict[int, Any]]
) -> dict[str, Any]:
    """Warm up (record the graphs) and measure one configuration on a loaded engine; returns its
    run (its chunks go to ``chunk_sets[config]``)."""
    import torch

    engine.use_sampler(engine_options(config))
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    if "-graphs" in config and "compiled" in config:
        # Layer by layer: the narrow π0.5 (the full one's depth) took 30 s for all four on a 2-core CPU.
        print(f"[{config}] compiling the static sampler's two layer functions, each for bucket 1 and for the other buckets", flush=True)
    engine.warmup(ARGS.max_batch_size, log_progress=False)
    warmup_s = time.perf_counter() - t0  # compilations and graph recordings included
    capture = dict(engine.sampler.capture_s) if engine.sampler is not None else {}
    print(f"[{config}] warmed up in {warmup_s:.0f} s: {engine.description}", flush=True)
    unrecorded = engine.unrecorded_batches
    engine_ms, bare_ms = measure(engine, ARGS.max_batch_size, ARGS.reps)
    got = chunk_sets[config] = chunks(engine)
    # A batch no recorded graph fits runs eagerly (logged once): a graphed figure must not hide one.
    unrecorded = engine.unrecorded_batches - unrecorded
    if unrecorded:
        print(f"  WARNING [{config}]: {unrecorded} timed or compared batches ran without their CUDA graph", flush=True)
    if "-graphs" not in config and "-compiled" not in config:
        reference[reference_key(config, overrides)] = got
    params = sum(p.numel() for p in engine.policy.parameters())
    run = {
        "policy": f"{engine.config.type} {ARGS.size if config != 'act' else ''}".strip(),
        "overrides": overrides,
        "engine_options": dataclasses.asdict(engine.engine_options),
        "params_millions": round(params / 1e6, 1),
        "compiled_kept": engine.compiled_kept,
        "engine_ms": [round(x, 2) for x in engine_ms],
        "bare_ms": [round(x, 2) for x in bare_ms],
        "reps": ARGS.reps,
        "warmup_s": round(warmup_s, 1),
    }
    if capture:
        run["capture_s"] = {str(b): round(s, 2) for b, s in sorted(capture.items())}
        run["unrecorded_batches"] = unrecorded
    ref = reference.get(reference_key(config, overrides))
    if ref is not None and ref is not got:
        # The same inputs through LeRobot's eager sampler on the same load, b = 1, 3, 8.
        run["vs_lerobot_eager"] = agreement(ref, got)
        print(f"  chunks vs LeRobot's eager sampler (b = 1, 3, 8): {run['vs_lerobot_eager']}", flush=True)
    if engine.sampler is not None and engine.sampler.vision_graphs:
        run["early_vision_batches"] = engine.sampler.early_starts  # batches whose tower started before the pre-processor
    late = chunk_sets.get(f"{config}-latevision")
    if late is not None:  # the vision tower started early must change no chunk: 0 expected
        run["vs_latevision"] = agreement(late, got)
        print(f"  chunks vs {config}-latevision (b = 1, 3, 8; 0 expected): {run['vs_latevision']}", flush=True)
    for other, before in chunk_sets.items():
        # The same engine with choices undone (as_before): zero keys masked, the same products
        # apart: only the sums' order may differ; with -mixedresidual the products' bf16 rounding too.
        suffix = other.removeprefix(f"{config}-")
        if other != suffix and set(suffix.split("-")) <= set(BEFORE):
            run[f"vs_{suffix}"] = agreement(before, got)
            print(f"  chunks vs {other} (b = 1, 3, 8): {run[f'vs_{suffix}']}", flush=True)
    if device == "cuda":
        run["peak_gpu_mib"] = round(torch.cuda.max_memory_allocated() / 2**20)
    return run


def float32_reference(runs: dict[str, Any], chunk_sets: dict[str, dict[int, Any]], work: Path, device: str, out: Path, name: str) -> None:
    """``run["vs_float32"]`` for every bf16 π0.5 and π0 configuration: how far its chunks are from
    LeRobot's eager sampler on the same weights computed in float32 (the bf16 directory loaded with
    ``--policy.dtype=float32``: bf16 values are exact in float32, so only the arithmetic differs)."""
    for kind in ("pi05", "pi0"):
        bf16 = [c for c in runs if c.startswith(f"{kind}-bf16") and c in chunk_sets]
        if bf16:
            _float32_reference(bf16, runs, chunk_sets, work, device, out, name)


def _float32_reference(bf16: list[str], runs: dict[str, Any], chunk_sets: dict[str, dict[int, Any]], work: Path, device: str, out: Path, name: str) -> None:
    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.engine.options import PolicyOptions

    path, _ = build(bf16[0], ARGS.size, work, ARGS.compile_mode)
    print(f"[float32 reference] loading {path} --policy.dtype=float32 (LeRobot's eager sampler)", flush=True)
    if device == "cuda":
        import torch

        torch.cuda.empty_cache()  # the last configuration's engine is gone; its cached blocks too
    try:
        engine = PolicyEngine(PolicyOptions(path, device, overrides=["dtype=float32"]), engine=engine_options("pi05-fp32"))
        want = chunks(engine)
    except Exception as exc:  # an extra: its failure loses no figure already written
        print(f"  float32 reference failed: {type(exc).__name__}: {str(exc).strip()[:200]}", flush=True)
        return
    del engine
    for config in bf16:
        runs[config]["vs_float32"] = agreement(want, chunk_sets[config])
        print(f"  {config}: chunks vs the float32 reference (b = 1, 3, 8): {runs[config]['vs_float32']}", flush=True)
    write(out, name, {config: runs[config] for config in bf16})


def add_kernels(engine: Any, run: dict[str, Any]) -> None:
    """``run["kernels"]``: :func:`kernel_breakdown` at b = 1 and the largest b (printed too)."""
    try:
        run["kernels"] = {str(b): kernel_breakdown(engine, b) for b in sorted({1, ARGS.max_batch_size})}
    except Exception as exc:  # the profiler is an extra: its failure loses nothing else
        print(f"  kernel breakdown failed: {type(exc).__name__}: {str(exc).strip()[:200]}", flush=True)
        return
    for b, k in run["kernels"].items():
        kinds = ", ".join(f"{kind} {ms:.1f}" for kind, ms in k["by_kind_ms"].items())
        print(f"  b={b}: {k['kernels']} kernels, {k['device_ms']:.1f} ms of kernel time a pass: {kinds}", flush=True)


def device_name(device: str) -> str:
    import torch

    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    return f"CPU {platform.processor() or platform.machine()} ({os.cpu_count()} cores)"


def write(out: Path, device: str, runs: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Merge ``runs`` into ``out`` (earlier calls' configurations are kept) and draw the figure."""
    data: dict[str, Any] = json.loads(out.read_text()) if out.is_file() else {}
    if data.get("device") not in (None, device):
        raise SystemExit(f"{out} holds {data['device']} figures; this is {device}: pass another --out")
    data.update({"device": device, "runs": {**data.get("runs", {}), **runs}})
    if not data["runs"]:
        return data  # nothing measured yet: nothing to write
    bf16 = [run for name, run in data["runs"].items() if name.startswith("pi05-bf16")]
    # The fastest π0.5 bf16 configuration is what a server would use; a file without one (π0,
    # SmolVLA) gets its own fastest configuration.
    served = min(bf16 or list(data["runs"].values()), key=lambda r: sum(r["engine_ms"]))
    data["name"] = f"{device} {served['policy']} (engine)"
    data["latency_ms"] = _non_decreasing(served["engine_ms"])
    data.pop("seed_h100_pi05_ms", None)
    data["jax_h100_pi05_ms"] = list(JAX_H100)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=2) + "\n")
    _plot(out.with_suffix(".png"), data)
    return data


def _non_decreasing(values: list[float]) -> list[float]:
    out: list[float] = []
    for v in values:
        out.append(round(max(v, out[-1]) if out else v, 2))
    return out


def _plot(path: Path, data: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, run in sorted(data["runs"].items()):
        b = range(1, len(run["engine_ms"]) + 1)
        line = ax.plot(b, run["engine_ms"], marker="o", label=f"{name} (engine)")[0]
        ax.plot(b, run["bare_ms"], linestyle="--", color=line.get_color(), label=f"{name} (bare)")
    ax.plot(range(1, len(JAX_H100) + 1), JAX_H100, color="black", marker="s", label="π0.5 in JAX (openpi), H100")
    ax.set_xlabel("batch size b")
    ax.set_ylabel("d_infer(b), ms")
    ax.set_yscale("log")
    ax.set_title(f"batched inference on {data['device']}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    import torch

    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.engine.options import EngineOptions, PolicyOptions

    device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cpu" and not ARGS.allow_cpu:
        print("gpu_profile: no CUDA device here; pass --allow_cpu to check the script (CPU figures, not GPU ones)", file=sys.stderr)
        sys.exit(2)
    name = device_name(device)
    slug = re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")
    out = Path(ARGS.out or (f"docs/results/gpu/{slug}.json" if device == "cuda" else f"out/gpu_profile/{slug}.json"))
    configs = [c.strip() for c in ARGS.configs.split(",") if c.strip()]
    unknown = [c for c in configs if c not in CONFIGS]
    if unknown:
        raise SystemExit(f"unknown config(s) {unknown}; known: {', '.join(CONFIGS)}")
    work = Path(ARGS.work_dir or tempfile.mkdtemp(prefix="armory-gpu-profile-"))
    print(f"device: {name}; configs: {', '.join(configs)}; b = 1..{ARGS.max_batch_size}; π0.5 / π0 size {ARGS.size}", flush=True)
    runs: dict[str, dict[str, Any]] = {}
    reference: dict[str, dict[int, Any]] = {}  # LeRobot's eager chunks, by dtype override
    chunk_sets: dict[str, dict[int, Any]] = {}  # every configuration's chunks
    failed: list[str] = []
    if ARGS.kernels and device == "cuda":
        # Start CUPTI before any graph is recorded (PyTorch's advice for profiling graph replays).
        init = getattr(getattr(torch.profiler, "_utils", None), "_init_for_cuda_graphs", None)
        if init is not None:
            init()
    engine, loaded = None, None
    for config in configs:
        path, overrides = build(config, ARGS.size, work, ARGS.compile_mode)
        # Configurations of one policy and dtype share a load, except after one that cast the vision
        # tower to bf16 (its float32 weights are gone).
        if (path, overrides) != loaded or (engine is not None and engine.vision_cast is not None):
            engine = None
            if device == "cuda":
                torch.cuda.empty_cache()
            print(f"[{config}] loading {path} {' '.join('--policy.' + o for o in overrides)}", flush=True)
            t0 = time.perf_counter()
            engine = PolicyEngine(PolicyOptions(path, device, overrides=overrides), engine=engine_options(config.split("-graphs")[0]))
            loaded = (path, overrides)
            print(f"  loaded in {time.perf_counter() - t0:.0f} s", flush=True)
        assert engine is not None
        with as_before(config):
            try:
                runs[config] = profile_config(engine, config, overrides, device, reference, chunk_sets)
            except Exception as exc:  # one configuration failing (a capture, say) must not lose the others
                failed.append(config)
                print(f"[{config}] FAILED: {type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}", flush=True)
                traceback.print_exc()
                continue
            if ARGS.stages:
                add_stages(engine, runs[config])
            write(out, name, {config: runs[config]})  # after each configuration: a time-out keeps what ran
            if ARGS.kernels and engine.sampler is not None:  # after the write: a profiler crash loses nothing
                add_kernels(engine, runs[config])
                write(out, name, {config: runs[config]})
    engine = None
    if ARGS.float32_reference:
        float32_reference(runs, chunk_sets, work, device, out, name)
    write(out, name, {})  # redraw the figure from everything written so far
    print(f"wrote {out} and {out.with_suffix('.png')} (load it with --latency_profile={out})")
    targets = Targets()
    if "H100" in name and ARGS.size == "full":
        for config, run in runs.items():
            if config.startswith("pi05-bf16-graphs"):
                for b, limit in GRAPH_TARGETS_H100.items():
                    if b <= len(run["engine_ms"]):
                        targets.check(f"{config} served b={b}", run["engine_ms"][b - 1], limit, "ms")
                if "capture_s" in run:
                    targets.check(f"{config} all buckets recorded", sum(run["capture_s"].values()), CAPTURE_TARGET_S, "s")
        for config, run in runs.items():  # the reference, no target: how far each is from JAX
            ratios = [f"{ms / ref:.2f}x" for ms, ref in zip(run["engine_ms"], JAX_H100)]
            print(f"  {config}: engine / JAX at b=1..5: {', '.join(ratios)}")
    else:
        print("  (the latency targets apply to π0.5 full bf16 with graphs on an H100; none checked here)")
    for config in failed:
        targets.misses.append(f"{config} (failed, see above)")
    targets.finish()


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--configs", default="pi05-bf16,act", help=f"comma-separated subset of {', '.join(CONFIGS)}")
    p.add_argument("--size", default="full", choices=("full", "tiny"), help="π0.5 and π0 size (tiny: to check the script)")
    p.add_argument("--max_batch_size", type=int, default=8)
    p.add_argument("--reps", type=int, default=10)
    p.add_argument("--compile_mode", default="reduce-overhead", help="torch.compile mode for the *-compiled configs")
    p.add_argument(
        "--kernels", action=argparse.BooleanOptionalAction, default=False,
        help="for the static sampler's configurations, trace one pass at b = 1 and the largest b with torch.profiler: "
        "kernel time by kind (matrix products, attention, norms, copies, elementwise) and the longest kernels",
    )  # fmt: skip
    p.add_argument(
        "--stages", action=argparse.BooleanOptionalAction, default=False,
        help="time each step of a served batch at b = 1 and the largest b, synchronised after each: stacking and upload, "
        "noise, pre-processor, forward, post-processor, copy back (where the engine's time over the bare pass goes)",
    )  # fmt: skip
    p.add_argument(
        "--float32_reference", action=argparse.BooleanOptionalAction, default=False,
        help="after the configurations, load the bf16 π0.5 again in float32 and give each bf16 configuration's chunk distance "
        "from LeRobot's eager float32 chunks on the same weights",
    )  # fmt: skip
    p.add_argument("--out", default=None, help="JSON to merge into (default docs/results/gpu/<device>.json on a GPU)")
    p.add_argument("--work_dir", default=None, help="where the policy directories are built (default: a temp dir)")
    p.add_argument("--graph_buckets", default=None, help="--engine.graph_buckets for the *-graphs configs (default 1,2,4,8)")
    p.add_argument("--allow_cpu", action="store_true", help="run without a GPU (script check; CPU figures)")
    return p.parse_args()


if __name__ == "__main__":
    ARGS = parse()
    main()
