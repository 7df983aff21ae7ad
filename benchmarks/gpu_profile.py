"""GPU latency profile: ``d_infer(b)`` of ACT and π0.5, through the engine and bare, b = 1..8.

Configurations (``--configs``, any subset; each is loaded through ``--policy.path`` like a user's):

- ``act``: ACT with 2 cameras 224², dim 512, 4 encoder layers (≈ 52 M parameters, random weights);
- ``pi05-fp32`` / ``pi05-bf16``: π0.5 ``full`` (PaliGemma gemma_2b + expert gemma_300m, random
  weights, stand-in tokenizer), ``--policy.dtype=float32|bfloat16``;
- ``pi05-fp32-compiled`` / ``pi05-bf16-compiled``: the same with ``--policy.compile_model=true``
  (``--compile_mode``; the engine keeps the compiled model only if it measured faster).

For each batch size: *engine* = ``PolicyEngine.infer`` on wire arrays (stacking, the uint8 upload,
pre-processor with the prompt's tokenizer, ``predict_action_chunk``, post-processor, the copy back)
and *bare* = ``predict_action_chunk`` alone on a batch already pre-processed on the device (the
model's own time; ``engine_efficiency.py``'s "bare" loop includes the pre/post-processors); both
median of ``--reps`` after the engine's warm-up, synchronised. Results merge into
``docs/results/gpu/<device>.json`` (one call per configuration fits the device tool's 10-minute
limit); its top-level ``latency_ms`` is π0.5 bf16 through the engine (the compiled run where it
was kept), so the file loads as ``--latency_profile=FILE``. A figure is drawn beside the seed's
H100 π0.5 table (SPEC §5).

Target (H100 only): π0.5 bf16 served at or below the seed's H100 latencies at b = 1..5.

    .venv/bin/python benchmarks/gpu_profile.py --configs=pi05-bf16,act
    .venv/bin/python benchmarks/gpu_profile.py --allow_cpu --size=tiny --out=out/cpu_profile.json   # script check only

Exits 1 on a missed target, 2 without a GPU unless ``--allow_cpu`` (whose figures are CPU figures
and are never written under docs/results/gpu by default).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets  # noqa: E402

CONFIGS = ("act", "pi05-fp32", "pi05-bf16", "pi05-fp32-compiled", "pi05-bf16-compiled")
SEED_H100 = (42.3, 56.0, 66.1, 79.3, 87.2)  # SPEC §5, π0.5 on an H100, ms at b = 1..5


def build(config: str, size: str, work: Path, compile_mode: str) -> tuple[str, list[str]]:
    """The policy directory of a configuration (built once per run) and its ``--policy.*`` overrides."""
    from lerobot_armory.server.demo_policy import DemoPolicyConfig, make_demo_policy

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
    path = work / f"pi05-{size}"
    if not (path / "config.json").is_file():
        print(f"building π0.5 {size} (random weights) in {path} ...", flush=True)
        t0 = time.perf_counter()
        make_demo_policy(
            DemoPolicyConfig(output=str(path), kind="pi05", size=size, chunk_size=50, state_dim=8, cameras="base,wrist", image_size=224)
        )
        print(f"  built in {time.perf_counter() - t0:.0f} s", flush=True)
    dtype = "bfloat16" if "bf16" in config else "float32"
    overrides = [f"dtype={dtype}"]
    if config.endswith("compiled"):
        overrides += ["compile_model=true", f"compile_mode={compile_mode}"]
    return str(path), overrides


def measure(engine: Any, max_b: int, reps: int) -> tuple[list[float], list[float]]:
    """Median ms per batch size: through the engine, and bare ``predict_action_chunk``."""
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
    """ms of ``predict_action_chunk`` alone on a batch already pre-processed on the device. Runs on
    the engine's device thread (via ``engine.on_device``), where the served forward passes run:
    a compiled model's CUDA graphs belong to that thread."""
    import torch

    batch = engine.to_batch(obs)
    batch["task"] = tasks
    kwargs = {"noise": engine._noise(seeds)} if engine.noise_shape is not None else {}
    times = []
    with torch.inference_mode():
        ready = engine.preprocessor(batch)
        sync()
        for _ in range(reps):
            t0 = time.perf_counter()
            engine.policy.predict_action_chunk(ready, **kwargs)
            sync()
            times.append((time.perf_counter() - t0) * 1000.0)
    return times


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
    served = data["runs"].get("pi05-bf16-compiled") or data["runs"].get("pi05-bf16")
    if served is None:  # no π0.5 bf16 yet: any run makes the file loadable
        served = next(iter(data["runs"].values()))
    data["name"] = f"{device} {served['policy']} (engine)"
    data["latency_ms"] = _non_decreasing(served["engine_ms"])
    data["seed_h100_pi05_ms"] = list(SEED_H100)
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
    ax.plot(range(1, len(SEED_H100) + 1), SEED_H100, color="black", marker="s", label="seed: H100 π0.5 (SPEC §5)")
    ax.set_xlabel("batch size b")
    ax.set_ylabel("d_infer(b), ms")
    ax.set_title(f"batched inference on {data['device']}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    import torch

    from lerobot_armory.server.engine import PolicyEngine, PolicyOptions

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
    print(f"device: {name}; configs: {', '.join(configs)}; b = 1..{ARGS.max_batch_size}; π0.5 size {ARGS.size}", flush=True)
    runs: dict[str, dict[str, Any]] = {}
    for config in configs:
        path, overrides = build(config, ARGS.size, work, ARGS.compile_mode)
        print(f"[{config}] loading {path} {' '.join('--policy.' + o for o in overrides)}", flush=True)
        t0 = time.perf_counter()
        engine = PolicyEngine(PolicyOptions(path, device, overrides=overrides))
        engine.warmup(ARGS.max_batch_size, log_progress=False)
        print(f"  loaded and warmed up in {time.perf_counter() - t0:.0f} s: {engine.description}", flush=True)
        engine_ms, bare_ms = measure(engine, ARGS.max_batch_size, ARGS.reps)
        params = sum(p.numel() for p in engine.policy.parameters())
        runs[config] = {
            "policy": f"{engine.config.type} {ARGS.size if config != 'act' else ''}".strip(),
            "overrides": overrides,
            "params_millions": round(params / 1e6, 1),
            "compiled_kept": engine.compiled_kept,
            "engine_ms": [round(x, 2) for x in engine_ms],
            "bare_ms": [round(x, 2) for x in bare_ms],
            "reps": ARGS.reps,
        }
        del engine
        if device == "cuda":
            torch.cuda.empty_cache()
    data = write(out, name, runs)
    print(f"wrote {out} and {out.with_suffix('.png')} (load it with --latency_profile={out})")
    targets = Targets()
    served = data["runs"].get("pi05-bf16-compiled") or data["runs"].get("pi05-bf16")
    if "H100" in name and served is not None and ARGS.size == "full":
        for b, seed in enumerate(SEED_H100, start=1):
            targets.check(f"π0.5 bf16 served b={b} vs seed H100", served["engine_ms"][b - 1], seed, "ms")
    else:
        print("  (the latency target applies to π0.5 full bf16 on an H100; none checked here)")
    targets.finish()


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--configs", default="pi05-bf16,act", help=f"comma-separated subset of {', '.join(CONFIGS)}")
    p.add_argument("--size", default="full", choices=("full", "tiny"), help="π0.5 size (tiny: to check the script)")
    p.add_argument("--max_batch_size", type=int, default=8)
    p.add_argument("--reps", type=int, default=10)
    p.add_argument("--compile_mode", default="reduce-overhead", help="torch.compile mode for the *-compiled configs")
    p.add_argument("--out", default=None, help="JSON to merge into (default docs/results/gpu/<device>.json on a GPU)")
    p.add_argument("--work_dir", default=None, help="where the policy directories are built (default: a temp dir)")
    p.add_argument("--allow_cpu", action="store_true", help="run without a GPU (script check; CPU figures)")
    return p.parse_args()


if __name__ == "__main__":
    ARGS = parse()
    main()
