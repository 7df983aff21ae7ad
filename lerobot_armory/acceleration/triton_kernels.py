"""Fused elementwise kernels for the π0 family's fused layers (``pi05_kernels.Fused``), in Triton.

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
  writing the float32 sum and the normed row);
- **the rotary embedding**: ``x · cos + swap_halves(x) · sin`` for q, k and v side by side (v's
  table the identity) — four kernels (the product with cos, the halves' swap as a ``cat``, two
  ``addcmul``, the keys' one non-vectorised as it writes into the cache's strided slice), 2.3 ms
  at b = 1 and 5.3 ms at b = 8 on an H200 (2026-11-28) (:func:`rope_qkv`: one kernel writing q
  and the cache's keys and values; 0.50 / 1.08 ms there);
- **attention's mask and softmax**: the mask added to the scores (broadcast over the heads, so
  non-vectorised) and the softmax — two kernels, 1.5 ms at b = 1 and 4.8 ms at b = 8
  (:func:`masked_softmax`: one kernel, in place; 0.86 / 2.74 ms there in two passes over each row,
  one pass since).

All compute in float32 and round once, on the way out (PyTorch's bf16 GELU rounds its output
before the product; the fused kernel does not). A CUDA graph records them like any other kernel:
Triton compiles each on its first call, which the graph's warm-up makes, never inside a recording.

They run where :func:`hand_kernels_reason` says they can: a CUDA device with Triton, checked once
against PyTorch's own operations on the device. On a CPU the sampler keeps PyTorch's operations;
the tests run these kernels through Triton's interpreter (``TRITON_INTERPRET=1``).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

_GELU_BLOCK = 1024  # columns a program of gelu_tanh_mul covers
# Keys a program of masked_softmax covers per pass over a row: one pass for π0.5's rows (at most
# ≈ 770 keys with two cameras), more for longer ones. Fixed, so that the row length is no constexpr:
# a new prompt bucket compiles no new kernel (and never inside a CUDA graph's recording).
_SOFTMAX_BLOCK = 1024


class LayerShape(NamedTuple):
    """What a model's layers hand the kernels: the widths of its residual stream and MLP, its
    query and key/value heads and their width."""

    width: int
    mlp_width: int
    heads: int
    kv_heads: int
    head_dim: int


def hand_kernels_reason(device: torch.device, dtype: torch.dtype, residual_dtype: torch.dtype, shapes: Sequence[LayerShape]) -> str | None:
    """Why the Triton kernels cannot run on ``device`` (None: they can). Each is run there once,
    on one row, for every shape it will see — ``shapes``: each model's — in the layers' ``dtype``,
    with products and gates of ``residual_dtype``, gated or not, and compared with PyTorch's
    operations: every variant Triton compiles is compiled here, at load, and a compiler or device
    that cannot run one is told before any batch. (Lengths and strides that vary with the batch
    or the prompt are not specialised on: no variant depends on them.)"""
    loose = _tolerance(dtype, residual_dtype)

    def check(rand: Any) -> str | None:
        for shape in sorted(set(shapes)):
            gate_up = rand(1, 2 * shape.mlp_width)
            gate, up = gate_up.float().chunk(2, dim=-1)
            if not torch.allclose(gelu_tanh_mul(gate_up).float(), torch.nn.functional.gelu(gate, approximate="tanh") * up, **loose):
                return f"the Triton GELU kernel disagreed with PyTorch's on {device} (MLP width {shape.mlp_width})"
            h = rand(1, shape.width, like=torch.float32)
            y, gate = rand(1, shape.width, like=residual_dtype), rand(1, shape.width, like=residual_dtype)
            weight = rand(shape.width, like=torch.float32).abs()
            for g in (gate, None):
                total, normed = add_rms_norm(h, y, g, weight, 1e-6, dtype)
                want = h + y.float() * (1.0 if g is None else g.float())
                if not (torch.allclose(total, want, **loose) and torch.allclose(normed.float(), torch.nn.functional.rms_norm(want, (shape.width,), weight, 1e-6), **loose)):
                    return f"the Triton norm kernel disagreed with PyTorch's on {device} (width {shape.width})"
        return None

    return _probe(device, dtype, check)


def attention_kernels_reason(device: torch.device, dtype: torch.dtype, shapes: Sequence[LayerShape]) -> str | None:
    """Why :func:`rope_qkv` and :func:`masked_softmax` cannot run on ``device`` (None: they can),
    checked as :func:`hand_kernels_reason` checks the others, apart from them: a kernel of these
    two that fails turns off these two only. Each runs once a shape, in each variant Triton will
    compile for it."""
    loose = _tolerance(dtype, dtype)

    def check(rand: Any) -> str | None:
        for shape in sorted(set(shapes)):
            heads, kv, d = shape.heads, 2 * shape.kv_heads, shape.head_dim
            # Two batch rows of two positions, into a cache's slice past its first position (as a
            # suffix is written): every stride is used, and the positions around stay as they were.
            qkv, cos, sin = (rand(2, 2, heads + kv, d) for _ in range(3))
            cache = rand(2, 4, kv, d)
            around = cache[:, ::3].clone()
            q = rope_qkv(qkv, cos, sin, heads, cache[:, 1:3])
            want = qkv.float() * cos.float() + torch.cat((qkv[..., d // 2 :], qkv[..., : d // 2]), dim=-1).float() * sin.float()
            rotated = torch.allclose(q.float(), want[:, :, :heads], **loose) and torch.allclose(cache[:, 1:3].float(), want[:, :, heads:], **loose)
            if not (rotated and torch.equal(cache[:, ::3], around)):
                return f"the Triton rotary kernel disagreed with PyTorch's on {device} ({heads} + {kv} heads of {d})"
            # Every variant: rows a multiple of 8 keys long or not, in one pass or two.
            for keys in (5, 16, _SOFTMAX_BLOCK + 5, _SOFTMAX_BLOCK + 8):
                scores, mask = rand(1, 1, heads, keys), torch.zeros(1, 1, 1, keys, device=device, dtype=dtype)
                mask[..., 2] = -1e30
                want = torch.softmax(scores.float() + mask.float(), dim=-1)
                if not torch.allclose(masked_softmax(scores, mask).float(), want, **loose):
                    return f"the Triton softmax kernel disagreed with PyTorch's on {device} ({heads} heads, {keys} keys)"
        return None

    return _probe(device, dtype, check)


def _probe(device: torch.device, dtype: torch.dtype, check: Callable[[Any], str | None]) -> str | None:
    """``check(rand)`` on ``device`` where a Triton kernel may run there at all: its answer, or why
    not (a compiler or driver that cannot build or run a kernel: PyTorch's operations serve)."""
    why = _unrunnable_reason(device)
    if why is not None:
        return why
    try:
        return check(_random(device, dtype))
    except torch.cuda.OutOfMemoryError:
        raise  # not an answer about the kernels: the load fails as it would have anyway
    except Exception as exc:  # noqa: BLE001 — a compiler or driver without them: PyTorch's ops serve
        text = str(exc).strip()
        return f"the Triton kernels failed on {device}: {text.splitlines()[0] if text else type(exc).__name__}"


def _unrunnable_reason(device: torch.device) -> str | None:
    """Why no Triton kernel can run on ``device`` at all (None: one may)."""
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
    return None


def _tolerance(*dtypes: torch.dtype) -> dict[str, float]:
    return {"atol": 0.05, "rtol": 0.02} if torch.bfloat16 in dtypes else {"atol": 1e-4, "rtol": 1e-4}


def _random(device: torch.device, dtype: torch.dtype) -> Any:
    """``rand(*shape, like=dtype)``: seeded normal values on ``device``, the same at every load."""
    gen = torch.Generator(device="cpu").manual_seed(0)

    def rand(*shape: int, like: torch.dtype = dtype) -> Tensor:
        return torch.randn(*shape, generator=gen).to(device=device, dtype=like)

    return rand


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


def rope_qkv(qkv: Tensor, cos: Tensor, signed_sin: Tensor, heads: int, dest: Tensor) -> Tensor:
    """The rotary embedding of a layer's q, k and v heads side by side (``pi05_kernels.Fused.rope``'s
    tables: q's scaled, v's the identity): ``x · cos + swap_halves(x) · signed_sin``, in float32,
    rounded once. ``qkv``, ``cos`` and ``signed_sin`` are ``(B, L, H + 2·Hkv, d)`` (the tables may
    have one batch row for all); returns q, a fresh ``(B, L, H, d)``, and writes k's and v's heads
    into ``dest`` ``(B, L, 2·Hkv, d)``, a cache's slice (each token's row contiguous)."""
    b, length, all_heads, d = qkv.shape
    kv = all_heads - heads
    tables_ok = all(t.shape[1:] == qkv.shape[1:] and t.shape[0] in (1, b) and t.is_contiguous() for t in (cos, signed_sin))
    if not tables_ok or cos.shape != signed_sin.shape or d % 2 or tuple(dest.shape) != (b, length, kv, d) or dest.stride()[2:] != (d, 1) or dest.stride(0) % d or dest.stride(1) % d:
        raise ValueError(f"rope_qkv: qkv {tuple(qkv.shape)}, tables {tuple(cos.shape)} / {tuple(signed_sin.shape)}, dest {tuple(dest.shape)} {dest.stride()}, {heads} query heads")
    qkv = qkv.contiguous()
    q = qkv.new_empty(b, length, heads, d)
    if qkv.numel():
        kernel = _kernels()[2]
        table_stride = cos.stride(0) if cos.shape[0] == b and b > 1 else 0
        with _on(qkv.device):
            strides = (qkv.stride(0), table_stride, q.stride(0), dest.stride(0), dest.stride(1))  # in elements: whole heads
            kernel[(length, b)](
                qkv, cos, signed_sin, q, dest, *(stride // d for stride in strides),
                HEADS=heads, ALL=all_heads, D=d, HEAD_BLOCK=_pow2(all_heads), BLOCK=_pow2(d // 2),
            )
    return q


def masked_softmax(scores: Tensor, mask: Tensor, one_pass: bool | None = None) -> Tensor:
    """``softmax(scores + mask)`` over the keys, in place, computed in float32, each probability
    rounded once: ``scores`` ``(B, Lq, H, Lk)`` contiguous, ``mask`` ``(B, Lq, 1, Lk)`` (additive,
    one row for all of a query's heads). Returns ``scores``, now the probabilities.

    A row of at most :data:`_SOFTMAX_BLOCK` keys is read once (``one_pass``; ``False`` forces the
    two passes longer rows take, for ``benchmarks/gpu/micro.py`` to time one against the other)."""
    b, lq, heads, length = scores.shape
    if tuple(mask.shape) != (b, lq, 1, length) or not scores.is_contiguous():
        raise ValueError(f"masked_softmax: scores {tuple(scores.shape)} (contiguous: {scores.is_contiguous()}), mask {tuple(mask.shape)}")
    mask = mask.contiguous()
    fits = length <= _SOFTMAX_BLOCK
    if one_pass and not fits:
        raise ValueError(f"masked_softmax: a row of {length} keys takes two passes (one holds {_SOFTMAX_BLOCK})")
    if scores.numel():
        kernel = _kernels()[3]
        with _on(scores.device):
            # Four variants at most: rows a multiple of 8 keys apart (π0.5's, whose caches are
            # aligned: 16 bytes in bf16) or not, in one pass or two; the load-time check compiles all.
            div = 8 if length % 8 == 0 else 1
            kernel[(b * lq,)](
                scores, mask, length // div, LENGTH_DIV=div, HEADS=heads, HEAD_BLOCK=_pow2(heads), BLOCK=_SOFTMAX_BLOCK,
                ONE_PASS=fits if one_pass is None else one_pass, num_warps=8,
            )  # fmt: skip
    return scores


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
def _kernels() -> tuple[Any, Any, Any, Any]:
    """The Triton kernels (GELU · up, residual + norm, rotary, masked softmax), jitted on first
    use: Triton reads ``TRITON_INTERPRET`` when a function is jitted, so a test sets it first.
    Strides and lengths that vary with the batch or the prompt are not specialised on (Triton
    would otherwise compile a variant for each divisibility by 16)."""
    import triton

    rope = triton.jit(_rope_qkv_kernel, do_not_specialize=["qkv_stride", "table_stride", "q_stride", "dest_stride", "dest_row"])
    softmax = triton.jit(_masked_softmax_kernel, do_not_specialize=["length"])
    return triton.jit(_gelu_tanh_mul_kernel), triton.jit(_add_rms_norm_kernel), rope, softmax


# The kernels' bodies: plain functions, jitted by _kernels(). Their reductions are ``tl.reduce``
# with Triton's own combine functions (what ``tl.sum`` and ``tl.max`` pass it): ``tl.sum`` itself
# is jitted when triton is imported, which Triton's CPU interpreter cannot run unless it was on by
# then, and with these combine functions the interpreter reduces in numpy, not one Python call a
# pair of elements. On a GPU it is the same reduction ``tl.sum`` / ``tl.max`` compile to.


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
    mean_square = tl.reduce(total * total, 0, tl.standard._sum_combine) / width
    scale = 1.0 / tl.sqrt(mean_square + eps)
    weight = tl.load(weight_ptr + cols, mask=inside, other=0.0).to(tl.float32)
    tl.store(normed_ptr + row + cols, (total * scale * weight).to(normed_ptr.dtype.element_ty), mask=inside)


def _rope_qkv_kernel(  # type: ignore[no-untyped-def]
    qkv_ptr, cos_ptr, sin_ptr, q_ptr, dest_ptr, qkv_stride, table_stride, q_stride, dest_stride, dest_row,
    HEADS: tl.constexpr, ALL: tl.constexpr, D: tl.constexpr, HEAD_BLOCK: tl.constexpr, BLOCK: tl.constexpr,  # type: ignore[name-defined]
):
    # One program a (position, batch row): all its heads, each as its two halves loaded contiguous
    # (an index taken modulo d would keep the loads from vectorising): the first half's sine term
    # reads the second half and the other way round. q's heads are stored to q, the others to the
    # cache's slice, by two masked stores.
    pos = tl.program_id(0).to(tl.int64)
    row = tl.program_id(1).to(tl.int64)
    # The strides come in heads (rows of whole heads: exact), times D here, so that the compiler
    # knows every offset a multiple of a head's width and the loads and stores vectorise
    # (unspecialised integers carry no divisibility of their own).
    qkv_stride, table_stride, q_stride = qkv_stride * D, table_stride * D, q_stride * D
    dest_stride, dest_row = dest_stride * D, dest_row * D
    head = tl.arange(0, HEAD_BLOCK)[:, None]
    half = tl.arange(0, BLOCK)[None, :]
    inside = (head < ALL) & (half < D // 2)
    at = (pos * ALL + head) * D + half
    src, table = qkv_ptr + row * qkv_stride + at, row * table_stride + at
    lo = tl.load(src, mask=inside, other=0.0).to(tl.float32)
    hi = tl.load(src + D // 2, mask=inside, other=0.0).to(tl.float32)
    cos_lo = tl.load(cos_ptr + table, mask=inside, other=0.0).to(tl.float32)
    cos_hi = tl.load(cos_ptr + table + D // 2, mask=inside, other=0.0).to(tl.float32)
    sin_lo = tl.load(sin_ptr + table, mask=inside, other=0.0).to(tl.float32)
    sin_hi = tl.load(sin_ptr + table + D // 2, mask=inside, other=0.0).to(tl.float32)
    out_lo, out_hi = lo * cos_lo + hi * sin_lo, hi * cos_hi + lo * sin_hi
    q = q_ptr + row * q_stride + (pos * HEADS + head) * D + half
    is_q = inside & (head < HEADS)
    tl.store(q, out_lo.to(q_ptr.dtype.element_ty), mask=is_q)
    tl.store(q + D // 2, out_hi.to(q_ptr.dtype.element_ty), mask=is_q)
    kv = dest_ptr + row * dest_stride + pos * dest_row + (head - HEADS) * D + half
    is_kv = inside & (head >= HEADS)
    tl.store(kv, out_lo.to(dest_ptr.dtype.element_ty), mask=is_kv)
    tl.store(kv + D // 2, out_hi.to(dest_ptr.dtype.element_ty), mask=is_kv)


def _masked_softmax_kernel(scores_ptr, mask_ptr, length, LENGTH_DIV: tl.constexpr, HEADS: tl.constexpr, HEAD_BLOCK: tl.constexpr, BLOCK: tl.constexpr, ONE_PASS: tl.constexpr):  # type: ignore[no-untyped-def,name-defined]
    # One program a (batch row, query): its heads' rows of scores, which share the query's mask row.
    # ONE_PASS (a row of at most BLOCK keys, every row π0.5 has): the rows read once, held in
    # registers, normalised and stored. Otherwise two passes: each row's running maximum and sum of
    # exponentials (rescaled as the maximum grows), then the probabilities, the rows read again.
    # Keys past the row read -inf: exp gives them 0. A maximum still -inf (every key so far -inf)
    # is taken as 0, so that -inf - -inf never makes a NaN.
    query = tl.program_id(0).to(tl.int64)
    length = length * LENGTH_DIV  # it comes divided by LENGTH_DIV: rows 16 bytes apart (aligned caches) vectorise
    head = tl.arange(0, HEAD_BLOCK)[:, None]
    cols = tl.arange(0, BLOCK)[None, :]
    scores = scores_ptr + (query * HEADS + head) * length
    # The mask's row read as a (heads, keys) block like the scores' (``head * 0``): the same layout,
    # so no conversion through shared memory between the two (a 1-D row would need one).
    mask = mask_ptr + query * length + head * 0
    if ONE_PASS:
        inside = (cols < length) & (head < HEADS)
        x = tl.load(scores + cols, mask=inside, other=float("-inf")).to(tl.float32)
        x = x + tl.load(mask + cols, mask=inside, other=0.0).to(tl.float32)
        top = tl.reduce(x, 1, tl.standard._elementwise_max)
        e = tl.exp(x - tl.where(top == float("-inf"), 0.0, top)[:, None])
        total = tl.reduce(e, 1, tl.standard._sum_combine)
        tl.store(scores + cols, (e / total[:, None]).to(scores_ptr.dtype.element_ty), mask=inside)
    else:
        top = tl.full((HEAD_BLOCK,), float("-inf"), tl.float32)
        total = tl.full((HEAD_BLOCK,), 0.0, tl.float32)
        for start in range(0, length, BLOCK):
            inside = (start + cols < length) & (head < HEADS)
            x = tl.load(scores + start + cols, mask=inside, other=float("-inf")).to(tl.float32)
            x = x + tl.load(mask + start + cols, mask=inside, other=0.0).to(tl.float32)
            new_top = tl.maximum(top, tl.reduce(x, 1, tl.standard._elementwise_max))
            shift = tl.where(new_top == float("-inf"), 0.0, new_top)
            total = total * tl.exp(top - shift) + tl.reduce(tl.exp(x - shift[:, None]), 1, tl.standard._sum_combine)
            top = new_top
        shift = tl.where(top == float("-inf"), 0.0, top)
        for start in range(0, length, BLOCK):
            inside = (start + cols < length) & (head < HEADS)
            x = tl.load(scores + start + cols, mask=inside, other=float("-inf")).to(tl.float32)
            x = x + tl.load(mask + start + cols, mask=inside, other=0.0).to(tl.float32)
            tl.store(scores + start + cols, (tl.exp(x - shift[:, None]) / total[:, None]).to(scores_ptr.dtype.element_ty), mask=inside)
