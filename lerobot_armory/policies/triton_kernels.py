"""Two fused elementwise kernels for the π0 family's fused layers (``pi05_kernels.Fused``), in Triton.

At batch 1 a sample is thousands of small kernels, each a few microseconds however little it
does (the action expert's 18 layers run at each of 10 steps). Two sequences in every layer are
elementwise work PyTorch runs as several kernels, each reading and writing the whole tensor:

- **the MLP's activation**: ``gelu_tanh(gate) · up`` on the two halves of the gate/up product —
  two kernels, on a GPU both in PyTorch's non-vectorised kernel where the halves are strided (the
  expert's; the VLM's MLP runs two products instead, one launch more) (:func:`gelu_tanh_mul`: one
  kernel after one product, reading the halves where they lie);
- **the residual sum and the norm after it**: ``h + y · gate``, then RMSNorm of that sum with its
  weight, then the cast to the projections' dtype — three kernels, the first in PyTorch's
  mixed-dtype kernel when ``y`` is bf16 (:func:`add_rms_norm`: one kernel, one program a row,
  writing the float32 sum and the normed row).

Both compute in float32 and round once, on the way out (PyTorch's bf16 GELU rounds its output
before the product; the fused kernel does not). A CUDA graph records them like any other kernel:
Triton compiles each on its first call, which the graph's warm-up makes, never inside a recording.

They run where :func:`hand_kernels_reason` says they can: a CUDA device with Triton, checked once
against PyTorch's own operations on the device. On a CPU the sampler keeps PyTorch's operations;
the tests run these kernels through Triton's interpreter (``TRITON_INTERPRET=1``).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

_GELU_BLOCK = 1024  # columns a program of gelu_tanh_mul covers


def hand_kernels_reason(device: torch.device, dtype: torch.dtype, residual_dtype: torch.dtype, widths: Sequence[tuple[int, int]]) -> str | None:
    """Why the Triton kernels cannot run on ``device`` (None: they can). Each is run there once,
    on one row, for every shape it will see — ``widths``: each model's (width, MLP width) — in
    the layers' ``dtype``, with products and gates of ``residual_dtype``, gated or not, and
    compared with PyTorch's operations: every variant Triton compiles is compiled here, at load,
    and a compiler or device that cannot run one is told before any batch."""
    if device.type != "cuda" and not interpreted():
        return "the Triton kernels run on CUDA only"
    if device.type == "cuda" and interpreted():  # its host copies would land inside a graph's recording
        return "TRITON_INTERPRET=1 is set (Triton's CPU interpreter, for tests): unset it to run them on the GPU"
    try:
        import triton  # noqa: F401
    except ImportError:
        return "triton is not installed"
    if device.type == "cuda" and torch.cuda.is_current_stream_capturing():  # never launch a probe into someone's graph
        return "a CUDA graph was being recorded when the sampler was built"
    loose = {"atol": 0.05, "rtol": 0.02} if torch.bfloat16 in (dtype, residual_dtype) else {"atol": 1e-4, "rtol": 1e-4}
    try:
        gen = torch.Generator(device="cpu").manual_seed(0)
        for width, mlp_width in sorted(set(widths)):
            gate_up = torch.randn(1, 2 * mlp_width, generator=gen).to(device=device, dtype=dtype)
            gate, up = gate_up.float().chunk(2, dim=-1)
            if not torch.allclose(gelu_tanh_mul(gate_up).float(), torch.nn.functional.gelu(gate, approximate="tanh") * up, **loose):
                return f"the Triton GELU kernel disagreed with PyTorch's on {device} (MLP width {mlp_width})"
            h = torch.randn(1, width, generator=gen).to(device)
            y, gate = (torch.randn(1, width, generator=gen).to(device=device, dtype=residual_dtype) for _ in range(2))
            weight = torch.rand(width, generator=gen).to(device)
            for g in (gate, None):
                total, normed = add_rms_norm(h, y, g, weight, 1e-6, dtype)
                want = h + y.float() * (1.0 if g is None else g.float())
                if not (torch.allclose(total, want, **loose) and torch.allclose(normed.float(), torch.nn.functional.rms_norm(want, (width,), weight, 1e-6), **loose)):
                    return f"the Triton norm kernel disagreed with PyTorch's on {device} (width {width})"
    except torch.cuda.OutOfMemoryError:
        raise  # not an answer about the kernels: the load fails as it would have anyway
    except Exception as exc:  # noqa: BLE001 — a compiler or driver without them: PyTorch's ops serve
        text = str(exc).strip()
        return f"the Triton kernels failed on {device}: {text.splitlines()[0] if text else type(exc).__name__}"
    return None


def interpreted() -> bool:
    """Whether Triton runs kernels on the CPU through its interpreter (``TRITON_INTERPRET=1``)."""
    import os

    return os.environ.get("TRITON_INTERPRET", "0") == "1"


def gelu_tanh_mul(gate_up: Tensor) -> Tensor:
    """``gelu_tanh(gate) · up`` for ``gate_up = [gate | up]`` along the last dimension (contiguous
    rows), in ``gate_up``'s dtype: ``(…, 2H)`` → ``(…, H)``, computed in float32, rounded once."""
    width = gate_up.shape[-1] // 2
    rows = gate_up.numel() // max(2 * width, 1)
    out = gate_up.new_empty(*gate_up.shape[:-1], width)
    if rows and width:
        gate_up = gate_up.contiguous()
        kernel = _kernels()[0]
        with _on(gate_up.device):
            kernel[(rows, -(-width // _GELU_BLOCK))](gate_up, out, width, BLOCK=_GELU_BLOCK)
    return out


def add_rms_norm(h: Tensor, y: Tensor, gate: Tensor | None, weight: Tensor, eps: float, out_dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``s = h + y · gate`` (``gate`` per channel, or none) and ``rms_norm(s) · weight`` in
    ``out_dtype``: ``h`` float32 ``(…, W)``, ``y`` of any float dtype and ``h``'s shape, ``gate``
    and ``weight`` ``W`` values. Returns ``(s, normed)``: ``s`` float32 (the residual stream)."""
    width = h.shape[-1]
    rows = h.numel() // max(width, 1)
    # One value a channel (the kernel reads the first ``width``): a per-row gate would be misread.
    if weight.numel() != width or (gate is not None and gate.numel() != width) or y.shape != h.shape:
        raise ValueError(f"add_rms_norm: h and y {tuple(h.shape)} / {tuple(y.shape)}, gate and weight one value a channel ({width})")
    h, y = h.contiguous(), y.contiguous()
    total = torch.empty_like(h, dtype=torch.float32)
    normed = torch.empty_like(h, dtype=out_dtype)
    if rows and width:
        kernel = _kernels()[1]
        gate_flat = weight if gate is None else gate.reshape(-1)  # a pointer either way; unread without a gate
        with _on(h.device):
            kernel[(rows,)](
                h, y, gate_flat, weight.reshape(-1), total, normed, width, eps, HAS_GATE=gate is not None, BLOCK=_pow2(width)
            )
    return total, normed


def _on(device: torch.device) -> Any:
    """Triton launches on the current CUDA device: make it the tensors' (a second GPU's policy)."""
    return torch.cuda.device(device) if device.type == "cuda" else contextlib.nullcontext()


def _pow2(n: int) -> int:
    return 1 << max(n - 1, 0).bit_length()


try:  # the kernels' bodies name ``tl``; without triton they are never jitted (hand_kernels_reason)
    import triton.language as tl
except ImportError:  # pragma: no cover - triton ships with PyTorch's Linux builds
    tl = None


@functools.cache
def _kernels() -> tuple[Any, Any]:
    """The two Triton kernels, jitted on first use: Triton reads ``TRITON_INTERPRET`` when a
    function is jitted, so a test sets it first, and the combine function the norm's reduction
    calls is jitted here too, in the same mode, and bound to the module name the kernel reads
    (Triton resolves a kernel's calls through its module's globals)."""
    import triton

    globals()["_add_jitted"] = triton.jit(_add)
    return triton.jit(_gelu_tanh_mul_kernel), triton.jit(_add_rms_norm_kernel)


# The kernels' bodies: plain functions, jitted by _kernels().


def _add(a, b):  # type: ignore[no-untyped-def]
    return a + b


def _gelu_tanh_mul_kernel(gate_up_ptr, out_ptr, width, BLOCK: tl.constexpr):  # type: ignore[no-untyped-def,name-defined]
    row = tl.program_id(0)
    cols = tl.program_id(1) * BLOCK + tl.arange(0, BLOCK)
    inside = cols < width
    base = gate_up_ptr + row.to(tl.int64) * 2 * width
    gate = tl.load(base + cols, mask=inside, other=0.0).to(tl.float32)
    up = tl.load(base + width + cols, mask=inside, other=0.0).to(tl.float32)
    inner = 0.7978845608028654 * (gate + 0.044715 * gate * gate * gate)  # sqrt(2 / pi): a literal, as Triton wants
    # tanh from exp, a core operation: library functions such as tl.sigmoid and tl.sum are jitted
    # when triton is imported, which Triton's CPU interpreter cannot run unless it was on by then.
    tanh = 1.0 - 2.0 / (tl.exp(2.0 * inner) + 1.0)
    out = 0.5 * gate * (1.0 + tanh) * up
    tl.store(out_ptr + row.to(tl.int64) * width + cols, out.to(out_ptr.dtype.element_ty), mask=inside)


def _add_rms_norm_kernel(  # type: ignore[no-untyped-def]
    h_ptr, y_ptr, gate_ptr, weight_ptr, total_ptr, normed_ptr, width, eps, HAS_GATE: tl.constexpr, BLOCK: tl.constexpr  # type: ignore[name-defined]
):
    row = tl.program_id(0).to(tl.int64) * width
    cols = tl.arange(0, BLOCK)
    inside = cols < width
    h = tl.load(h_ptr + row + cols, mask=inside, other=0.0).to(tl.float32)
    y = tl.load(y_ptr + row + cols, mask=inside, other=0.0).to(tl.float32)
    if HAS_GATE:
        y = y * tl.load(gate_ptr + cols, mask=inside, other=0.0).to(tl.float32)
    total = h + y
    tl.store(total_ptr + row + cols, total, mask=inside)
    mean_square = tl.reduce(total * total, 0, _add_jitted) / width  # noqa: F821 - bound by _kernels()
    scale = 1.0 / tl.sqrt(mean_square + eps)
    weight = tl.load(weight_ptr + cols, mask=inside, other=0.0).to(tl.float32)
    tl.store(normed_ptr + row + cols, (total * scale * weight).to(normed_ptr.dtype.element_ty), mask=inside)
