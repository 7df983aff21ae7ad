"""How far bf16 chunks lie from a float32 model's: LeRobot's bf16 sampler against the static
sampler's two orders of operations, on the CPU, for π0.5 and π0 at their real depths.

Why a benchmark: the fused kernels keep the residual stream (and the last norm's output) in
float32 where LeRobot's bf16 layers round them to bf16, and the claim that this brings bf16
chunks nearer float32 must hold on more than one random model. A random-weight π0.5 is a
flattering case: its adaptive norms' weights are zero-initialised (LeRobot's ``PiGemmaRMSNorm``),
so every action-expert layer's gate is the dense layer's small random bias (mean |gate| ≈ 0.065
on the narrow π0.5) and damps that layer's bf16 products fifteenfold. A trained π0.5's gates are
not known to be small. So three models, each built offline with random weights and loaded
twice, ``--policy.dtype=float32`` (the reference) and ``bfloat16`` (every Gemma weight rounded):

- ``pi05``: the narrow π0.5 as built;
- ``pi05-gated``: the same weights with every expert norm's gate bias raised by 1 (gates ≈ 1, each
  layer's products undamped: the unflattering case);
- ``pi0``: the narrow π0 (no adaptive norms, no gates).

Per model and batch size: the largest and mean |chunk - float32 chunk| of LeRobot's bf16 sampler,
of the static sampler in LeRobot's order (``--engine.fused_kernels=false``: LeRobot's bf16
rounding, so about LeRobot's distance) and fused (the default). Target, a regression guard:
fused's largest distance at most 1.5× LeRobot's on every model and size (a fused kernel that
computed something else, like conditioning made before the weights changed, is 100× off; the
ratio itself moves with the inputs: 0.6–1.3 over 16 input sets on the tiny π0). Exits 1 on a miss. CPU figures (bf16
arithmetic on a CPU rounds like a GPU's in kind, not bit for bit); on a GPU the same comparison
is ``gpu_profile.py --float32_reference``.

    .venv/bin/python benchmarks/bf16_accuracy.py [--sizes=1,3]   # ≈ 1 min on 2 cores
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets  # noqa: E402

RATIO = 1.5  # a guard, not a claim: the ratio moves with the inputs (0.6–1.3 on the tiny π0)


def raise_gates(path: Path, by: float) -> int:
    """Add ``by`` to the gate third of every action-expert adaptive norm's bias in the saved
    weights at ``path``; returns how many norms were changed."""
    from safetensors.torch import load_file, save_file

    file = path / "model.safetensors"
    weights = load_file(file)
    changed = 0
    for name, tensor in weights.items():
        if "gemma_expert" in name and name.endswith("dense.bias"):
            third = tensor.shape[0] // 3
            tensor[2 * third :] += by
            changed += 1
    save_file(weights, file, metadata={"format": "pt"})
    return changed


def distances(path: str, sizes: list[int]) -> dict[int, dict[str, tuple[float, float]]]:
    """Per batch size, per sampler: (largest, mean) |chunk - float32 chunk|."""
    import numpy as np

    from lerobot_armory.engine.options import EngineOptions, PolicyOptions
    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.engine.protocol import noise_seed

    bf16 = ["dtype=bfloat16"]
    reference = PolicyEngine(PolicyOptions(path, "cpu"))
    samplers: dict[str, Any] = {
        "LeRobot bf16": PolicyEngine(PolicyOptions(path, "cpu", overrides=bf16)),
        "ordered bf16": PolicyEngine(PolicyOptions(path, "cpu", overrides=bf16), engine=EngineOptions(static_sampler=True, fused_kernels=False)),
        "fused bf16": PolicyEngine(PolicyOptions(path, "cpu", overrides=bf16), engine=EngineOptions(static_sampler=True)),
    }
    out: dict[int, dict[str, tuple[float, float]]] = {}
    for b in sizes:
        obs = [reference.example_observation(seed=k) for k in range(b)]
        tasks = [f"pick up block {k}" for k in range(b)]
        seeds = [noise_seed(f"robot{k}", 0) for k in range(b)]
        want = reference.infer(obs, tasks, seeds)
        out[b] = {}
        for name, engine in samplers.items():
            d = np.abs(engine.infer(obs, tasks, seeds) - want)
            out[b][name] = (float(d.max()), float(d.mean()))
    return out


def main() -> None:
    import torch

    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="1,3", help="batch sizes")
    args = p.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    torch.set_num_threads(2)
    work = Path(tempfile.mkdtemp(prefix="armory-bf16-"))
    t0 = time.perf_counter()
    paths = {}
    for kind in ("pi05", "pi0"):
        paths[kind] = work / f"{kind}-narrow"
        make_demo_policy(DemoPolicyConfig(output=str(paths[kind]), kind=kind, size="narrow", chunk_size=10, seed=0))
    paths["pi05-gated"] = work / "pi05-gated"
    shutil.copytree(paths["pi05"], paths["pi05-gated"])
    changed = raise_gates(paths["pi05-gated"], 1.0)
    print(f"built the narrow π0.5 and π0 and a π0.5 with {changed} norms' gates raised (the final norm's is unused) in {time.perf_counter() - t0:.0f} s (CPU, 2 threads)")
    print(f"{'model':<11} | {'b':>2} | {'sampler':<13} | {'largest':>8} | {'mean':>8}")
    targets = Targets()
    for model in ("pi05", "pi05-gated", "pi0"):
        for b, rows in distances(str(paths[model]), sizes).items():
            for name, (largest, mean) in rows.items():
                print(f"{model:<11} | {b:>2} | {name:<13} | {largest:>8.2e} | {mean:>8.2e}")
            targets.check(f"{model} b={b}: fused / LeRobot's largest distance", rows["fused bf16"][0] / rows["LeRobot bf16"][0], RATIO, "")
    shutil.rmtree(work, ignore_errors=True)
    targets.finish()


if __name__ == "__main__":
    main()
