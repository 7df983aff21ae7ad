"""Kernels per π0.5 (or π0) batch, counted on a CPU: LeRobot's eager sampler against our static sampler.

On a GPU, LeRobot 0.6.1's π0.5 is bound by kernel launches, and a CUDA graph can only record a
region that never waits for the host. Neither needs a GPU to be seen: this script builds the
*narrow* π0.5 (``lerobot-armory-make-demo-policy --kind=pi05 --size=narrow``: LeRobot's real depths
— 18 + 18 Gemma layers, 27 SigLIP layers, 8 query heads on one K/V head, two 224² cameras, a
200-token prompt, chunk 50 — at tiny widths), loads it through ``--policy.path`` twice (LeRobot's
sampler; ``--engine.static_sampler=true``) and, for each batch size, counts the aten ops of one
forward pass (``PolicyEngine.forward`` on a pre-processed batch, i.e. the region a graph records):

- *launches*: ops that compute (views and allocations excluded) ≈ kernels a GPU would launch;
- *host syncs*: ops that wait for the host (``torch.tensor(list, device=…)``, ``.item()``, …), each
  of which makes a CUDA graph capture fail;
  (the static sampler's count is of the recorded region; before it, once a batch, the engine reads
  the prompt masks back to choose the prompt bucket);
- a ``torch._dynamo.explain`` trace of the static sampler: graphs and graph breaks;
- CPU ms per forward pass (median of 5): CPU figures, printed for the record, not GPU ones.

Targets: the static sampler has no host sync and traces as one graph with no break at every
size (what a capture needs); with its fused layers (the default) it launches at most 0.4×
LeRobot's kernels (a regression guard: 0.32–0.35× measured on 2026-11-27, in float32 and bf16;
what remains is the model's own arithmetic, about 20 kernels an expert layer and step, which
only ``--engine.compile_sampler`` reduces further). Exits 1 on a miss. ``--kind=pi0`` counts
LeRobot's π0 the same way (the same depths, a 48-token prompt, the state as a token of the
action expert's suffix); ``--kind=smolvla`` LeRobot's SmolVLA (SmolVLM2-500M's depths and image
geometry at tiny widths, float32 only; its fused kernels are ``acceleration/smolvla_kernels.py``).

    .venv/bin/python benchmarks/pi05_ops.py [--sizes=1,8] [--dtype=bfloat16] [--kind=pi0|smolvla]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets  # noqa: E402

LAUNCH_RATIO = 0.4


def forward_inputs(engine: Any, b: int) -> tuple[dict, dict]:
    """A pre-processed batch of b example observations and the forward pass's keyword arguments."""
    import torch

    batch = engine.to_batch([engine.example_observation(seed=k) for k in range(b)])
    batch["task"] = [f"pick up block {k}" for k in range(b)]
    with torch.inference_mode():
        return engine.preprocessor(batch), {"noise": engine._noise(range(b))}


def count(engine: Any, b: int) -> tuple[Any, float]:
    """(OpTrace of one forward pass, median CPU ms of 5)."""
    import torch

    from lerobot_armory.acceleration.op_trace import OpTrace

    processed, kwargs = forward_inputs(engine, b)
    # no_grad, not inference_mode: composite ops then reach the trace decomposed, with the copies
    # they make (acceleration/op_trace.py).
    with torch.no_grad():
        if engine.sampler is None:
            def forward() -> Any:
                return engine.forward(processed, kwargs)
        else:  # the recorded region alone: the prompt bucket is chosen (read back) before it
            inputs = engine._sampler_inputs(processed, kwargs)

            def forward() -> Any:
                return engine.sampler(inputs)
        forward()  # first pass: lazy initialisations
        with OpTrace() as trace:
            forward()
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            forward()
            times.append((time.perf_counter() - t0) * 1000.0)
    return trace, statistics.median(times)


def trace_graphs(engine: Any, b: int) -> tuple[int, int, list[str]]:
    """(graphs, graph breaks, reasons) of the static sampler at batch size b under dynamo."""
    import torch
    import torch._dynamo

    processed, kwargs = forward_inputs(engine, b)
    inputs = engine._sampler_inputs(processed, kwargs)
    torch._dynamo.reset()
    sample = engine.sampler.sample
    with torch.inference_mode():
        explained = torch._dynamo.explain(sample)(inputs)
    return explained.graph_count, explained.graph_break_count, [str(r.reason).splitlines()[0] for r in explained.break_reasons]


def main() -> None:
    import torch

    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy
    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.engine.cuda_graphs import bucket_for
    from lerobot_armory.engine.options import EngineOptions, PolicyOptions

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="1,8", help="batch sizes to count")
    p.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"), help="--policy.dtype (bf16 keeps LeRobot's float32 islands)")
    p.add_argument("--kind", default="pi05", choices=("pi05", "pi0", "smolvla"), help="the policy type")
    args = p.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    if args.kind == "smolvla" and args.dtype != "float32":
        sys.exit("SmolVLA is built in float32 only")
    overrides = [] if args.kind == "smolvla" else [f"dtype={args.dtype}"]  # SmolVLA's config has no dtype
    torch.set_num_threads(1)
    work = Path(tempfile.mkdtemp(prefix="armory-pi05-ops-"))
    path = str(work / f"{args.kind}-narrow")
    t0 = time.perf_counter()
    make_demo_policy(
        DemoPolicyConfig(output=path, kind=args.kind, size="narrow", chunk_size=50, state_dim=8, cameras="base,wrist", image_size=224)
    )
    eager = PolicyEngine(PolicyOptions(path, "cpu", cpu_threads=1, overrides=overrides))
    ordered = PolicyEngine(PolicyOptions(path, "cpu", cpu_threads=1, overrides=overrides), engine=EngineOptions(static_sampler=True, fused_kernels=False))
    static = PolicyEngine(PolicyOptions(path, "cpu", cpu_threads=1, overrides=overrides), engine=EngineOptions(static_sampler=True))
    ordered.warmup(max(sizes), log_progress=False)
    static.warmup(max(sizes), log_progress=False)
    params = sum(p.numel() for p in eager.policy.parameters()) / 1e6
    name = {"pi05": "π0.5", "pi0": "π0", "smolvla": "SmolVLA"}[args.kind]
    print(f"{name} narrow, {args.dtype} ({params:.1f} M parameters, built and loaded in {time.perf_counter() - t0:.0f} s); CPU, 1 thread")
    print(f"{'b':>2} | {'sampler':<8} | {'aten ops':>8} | {'launches':>8} | {'host syncs':>10} | {'CPU ms':>7} | most launched")
    targets = Targets()
    for b in sizes:
        rows = {}
        for name, engine in (("LeRobot", eager), ("ordered", ordered), ("fused", static)):
            trace, ms = count(engine, b)
            rows[name] = trace
            syncs = sum(trace.host_syncs.values())
            top = ", ".join(f"{op.split('.')[1]} {n}" for op, n in trace.top(4))
            print(f"{b:>2} | {name:<8} | {trace.total:>8} | {trace.launches:>8} | {syncs:>10} | {ms:>7.1f} | {top}")
        ratio = rows["fused"].launches / rows["LeRobot"].launches
        print(
            f"   launches ordered / LeRobot: {rows['ordered'].launches / rows['LeRobot'].launches:.3f}, fused / LeRobot: {ratio:.3f}; "
            f"LeRobot's host syncs: {dict(rows['LeRobot'].host_syncs)}; static: {dict(rows['fused'].host_syncs)}"
        )
        for name in ("ordered", "fused"):
            targets.check(f"b={b}: {name} static sampler host syncs", sum(rows[name].host_syncs.values()), 0, "ops")
        targets.check(f"b={b}: launches fused / LeRobot", ratio, LAUNCH_RATIO, "")
    for b in sorted({bucket_for(b, static.sampler.buckets) for b in sizes}):  # the buckets the sizes run in
        t0 = time.perf_counter()
        graphs, breaks, reasons = trace_graphs(static, b)
        print(f"   dynamo trace of the static sampler at bucket {b}: {graphs} graph(s), {breaks} break(s) ({time.perf_counter() - t0:.0f} s){' ' + '; '.join(reasons) if reasons else ''}")
        targets.check(f"bucket {b}: graph breaks", breaks, 0, "")
        targets.check(f"bucket {b}: graphs", graphs, 1, "")
    targets.finish()


if __name__ == "__main__":
    main()
