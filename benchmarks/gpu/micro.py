"""The fused π0.5 layers' GPU-only choices, one kernel at a time, at the full π0.5's shapes.

Each choice made on 2026-11-28 #10 (``acceleration/pi05_kernels.py``, ``acceleration/triton_kernels.py``)
against what it replaced, checked for equal values and timed on its own, at the rows a sample
runs at b = 1 and b = 8 (VLM: 576 prefix rows a sample, LIBERO's two cameras and a 64-token
prompt; expert: 50 action rows):

- the MLP's activation: PyTorch's GELU and product on one product's strided halves, the same on
  two contiguous products' outputs (the VLM's ``apart``), and the Triton kernel on the halves;
- a residual sum with the norm and cast after it: PyTorch's ``addcmul`` (mixed-dtype: bf16 product
  and gate on the float32 stream), ``rms_norm`` and cast, against the Triton kernel;
- the output and down projections: bf16 out against float32 out (``mm(out_dtype=float32)``);
- (2026-11-28 #11) the rotary embedding of q, k and v with the keys and values written into the
  cache: PyTorch's four kernels against the Triton kernel;
- (2026-11-28 #11) attention's mask and softmax: PyTorch's add and softmax against the Triton
  kernel (the expert's rows attend the prefix's keys and their own, 632);
- (2026-11-28 #12) the softmax kernel reading a row once (every π0.5 row fits its block) against
  its two passes (2026-11-28 #11's, which read each row twice).

Times are the median of CUDA-graph replays (``triton.testing.do_bench_cudagraph``), so launch
gaps are gone as in the served graphs. A few seconds on a GPU; it says, before the whole-sampler
figures of ``gpu_profile.py``, which choice pays at which size. Writes ``--out`` (JSON) and exits
non-zero if a choice computes other values than what it replaced (bf16 tolerances).
``--allow_cpu`` checks the script on a CPU (Triton's interpreter, small widths, host timer: a
script check, not a figure).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

# π0.5's two Gemmas: (width, MLP width, attention output width); rows a sample; keys a row attends.
FULL = {"vlm": (2048, 16384, 2048), "expert": (1024, 4096, 2048)}
ROWS = {"vlm": 576, "expert": 50}
KEYS = {"vlm": 576, "expert": 632}  # the expert's: the prefix and its 50, rounded up to 8 (the aligned cache)
HEADS, KV_HEADS, HEAD_DIM = 8, 1, 256  # both Gemmas'; on a CPU a head of 8


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1,8", help="batch sizes (rows = a sample's rows times b)")
    parser.add_argument("--out", default="out/gpu/micro.json")
    parser.add_argument("--allow_cpu", action="store_true", help="check the script on a CPU (interpreter, small widths)")
    args = parser.parse_args()
    if args.allow_cpu:
        os.environ["TRITON_INTERPRET"] = "1"  # before the kernels are jitted
    import torch

    cuda = torch.cuda.is_available()
    if not cuda and not args.allow_cpu:
        sys.exit("no CUDA device: --allow_cpu checks the script on a CPU")
    device = torch.device("cuda" if cuda else "cpu")
    shapes = FULL if cuda else {k: (w // 32, m // 32, a // 32) for k, (w, m, a) in FULL.items()}
    sizes = [int(b) for b in args.sizes.split(",")] if cuda else [1]
    results: list[dict[str, Any]] = []
    wrong: list[str] = []
    for model, (width, mlp_width, attn_width) in shapes.items():
        for b in sizes:
            rows = ROWS[model] * b if cuda else 8
            attention = (b, ROWS[model], KEYS[model], HEAD_DIM) if cuda else (1, 8, 12, 8)
            for name, pair in cases(torch, device, rows, width, mlp_width, attn_width, attention).items():
                old, new = pair
                ref, got = old(), new()
                diff = (got.float() - ref.float()).abs().max().item()
                scale = ref.float().abs().max().item() or 1.0
                ok = diff <= 0.02 * scale + 1e-3  # bf16 roundings in either
                row = {"model": model, "b": b, "rows": rows, "case": name, "old_ms": timed(old, cuda), "new_ms": timed(new, cuda), "max_abs_diff": diff, "ok": ok}
                results.append(row)
                print(f"{model:6s} b={b} rows={rows:5d} {name:22s} old {row['old_ms']:8.4f} ms  new {row['new_ms']:8.4f} ms  "
                      f"new/old {row['new_ms'] / max(row['old_ms'], 1e-9):5.2f}  diff {diff:.2e}{'' if ok else '  WRONG'}", flush=True)  # fmt: skip
                if not ok:
                    wrong.append(f"{model} b={b} {name}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    device_name = torch.cuda.get_device_name() if cuda else "cpu (script check, interpreter: not a figure)"
    out.write_text(json.dumps({"device": device_name, "torch": torch.__version__, "results": results}, indent=1))
    print(f"wrote {out}")
    if wrong:
        sys.exit(f"values differ: {', '.join(wrong)}")


def cases(
    torch: Any, device: Any, rows: int, width: int, mlp_width: int, attn_width: int, attention: tuple[int, int, int, int]
) -> dict[str, tuple[Callable[[], Any], Callable[[], Any]]]:
    """Each choice as (what it replaced, the choice), closures over fresh random inputs;
    ``attention``: (batch rows, query rows a batch row, keys, head width)."""
    from lerobot_armory.acceleration.triton_kernels import add_rms_norm, gelu_tanh_mul, masked_softmax, rope_qkv

    gen = torch.Generator(device="cpu").manual_seed(0)

    def rand(*shape: int, dtype: Any = torch.bfloat16, scale: float = 1.0) -> Any:
        return (scale * torch.randn(*shape, generator=gen)).to(device=device, dtype=dtype)

    gelu = torch.nn.functional.gelu
    gate_up = rand(rows, 2 * mlp_width, scale=2.0)
    gate_alone, up_alone = (t.contiguous() for t in gate_up.chunk(2, dim=-1))
    h, weight = rand(rows, width, dtype=torch.float32, scale=3.0), (1 + rand(width, dtype=torch.float32, scale=0.1))
    y, gate = rand(rows, width), rand(width, scale=0.5)
    y32, gate32 = y.float(), gate.float()
    x, w = rand(rows, attn_width), rand(width, attn_width, scale=attn_width**-0.5)
    mm = torch.mm if device.type == "cuda" else (lambda a, b, out_dtype=None: torch.mm(a.float(), b.float()))

    def strided() -> Any:
        g, u = gate_up.chunk(2, dim=-1)
        return gelu(g, approximate="tanh") * u

    def eager_norm() -> Any:
        s = torch.addcmul(h, y, gate)
        return torch.nn.functional.rms_norm(s, (width,), weight, 1e-6).to(torch.bfloat16)

    b, queries, keys, d = attention
    all_heads = HEADS + 2 * KV_HEADS
    qkv, cos, sin = (rand(b, queries, all_heads, d) for _ in range(3))
    cache = rand(b, keys, 2 * KV_HEADS, d)
    dest = cache[:, keys - queries :]  # a suffix's place, as the expert writes it (the VLM's: all)
    scores = rand(b, queries, HEADS, keys, scale=3.0)
    mask = torch.where(torch.rand(b, queries, 1, keys, generator=gen) < 0.2, -2.3819763e38, 0.0).to(device=device, dtype=torch.bfloat16)

    def eager_rope() -> Any:  # pi05_kernels.Fused.qkv without the kernel
        rotated, swapped = qkv * cos, torch.cat((qkv[..., d // 2 :], qkv[..., : d // 2]), dim=-1)
        torch.addcmul(rotated[:, :, HEADS:], swapped[:, :, HEADS:], sin[:, :, HEADS:], out=dest)
        return torch.addcmul(rotated[:, :, :HEADS], swapped[:, :, :HEADS], sin[:, :, :HEADS])

    def softmax_copy() -> Any:  # what the sampler's own scores would be: a fresh product's output
        return scores.clone()

    return {
        "rope: aten -> triton": (eager_rope, lambda: rope_qkv(qkv, cos, sin, HEADS, dest)),
        "softmax: aten -> triton": (lambda: torch.softmax(softmax_copy().add_(mask), dim=-1), lambda: masked_softmax(softmax_copy(), mask)),
        "softmax: 2 passes -> 1": (lambda: masked_softmax(softmax_copy(), mask, one_pass=False), lambda: masked_softmax(softmax_copy(), mask)),
        "gelu: strided -> triton": (strided, lambda: gelu_tanh_mul(gate_up)),
        "gelu: strided -> apart": (strided, lambda: gelu(gate_alone, approximate="tanh") * up_alone),
        "norm: aten -> triton": (eager_norm, lambda: add_rms_norm(h, y, gate, weight, 1e-6, torch.bfloat16)[1]),
        "norm: bf16 y -> f32 y": (eager_norm, lambda: add_rms_norm(h, y32, gate32, weight, 1e-6, torch.bfloat16)[1]),
        "out proj: bf16 -> f32": (lambda: torch.mm(x, w.t()), lambda: mm(x, w.t(), out_dtype=torch.float32)),
    }


def timed(fn: Callable[[], Any], cuda: bool) -> float:
    """Median milliseconds of ``fn``: CUDA-graph replays on a GPU, a host timer on a CPU."""
    if cuda:
        import triton.testing

        return float(triton.testing.do_bench_cudagraph(fn, rep=50, return_mode="median"))
    fn()
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1000.0


if __name__ == "__main__":
    main()
