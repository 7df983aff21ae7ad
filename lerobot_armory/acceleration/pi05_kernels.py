"""The operations of one π0.5 transformer layer, two ways: LeRobot's own sequence, and fewer kernels.

The static sampler (``pi05_static.py``) runs the same loop either way; what differs is how many
kernels each layer launches. On a GPU under a CUDA graph the launch cost is gone but every kernel
still takes a few microseconds however small its work, and π0.5 at batch 1 is mostly small kernels:
the action expert runs 18 layers at each of 10 denoising steps. At full depth a sample launches
9,135 kernels in LeRobot's sequence and 4,012 fused in float32; 10,169 and 4,415 in bfloat16
(``benchmarks/pi05_ops.py``).

:class:`LeRobotOrder` is LeRobot's and HF's arithmetic, operation for operation (the reference:
bit for bit LeRobot's chunks on a CPU). :class:`Fused` computes the same values with fewer kernels:

- **one projection for q, k and v, and one for the MLP's gate and up** — the layer's q/k/v (and
  gate/up) weights are made *views* of one concatenated tensor (:func:`fuse_weights`): no weight
  is copied, none changes value, and LeRobot's modules keep working on them; except where an MLP
  runs over many rows (``apart``: the VLM's, over the prefix), whose gate and up stay two
  products, each written contiguous: one product's halves are strided, and PyTorch runs the
  activation and the product of the halves in its non-vectorised elementwise kernel (on an H200
  at b = 8, 9.4 of 80 ms, where the bytes they move take ≈ 3 ms), which costs more than the
  second launch (17 a sample);
- **RMSNorm as one kernel** (``torch.nn.functional.rms_norm``: ``_fused_rms_norm`` on CUDA, where
  LeRobot's ``square, mean, add, rsqrt, mul`` is five), the plain norm's ``1 + weight`` computed
  once; the **adaptive norm's time conditioning folded away** (:meth:`Fused.fold`, once per
  policy): its scale is the norm's weight and its shift the next projection's bias
  (``W(n·s + t) = W(n·s) + W·t``, the bias added in the matrix product), so an adaptive norm is
  one kernel where LeRobot's is six;
- **the rotary embedding of q, k and v together, with the attention scale folded into q's table**
  (HF's is four kernels each for q and k plus a scale on the scores): v's rows of the table are
  cos 1, sin 0, so v passes unrotated, bit for bit; the rotation's last kernel runs once for q's
  rows (a fresh q, in the layout attention reads) and once for k's and v's, **stored straight
  into the K/V cache** (LeRobot's order: two copies a layer pass, HF's cache a concatenation);
- **attention in the projection's layout**: with one K/V head (π0.5: eight query heads on one),
  every (token, head) query row attends the same keys, so the scores, the softmax and the
  weighted sum run on q's ``(B, L·heads, d)`` rows and on k and v where they lie in the cache, and
  the output is the ``(B, L, heads·d)`` the output projection takes (HF transposes q and the
  output and copies K/V per query head);
- **gated residuals and the Euler step as one kernel each** (``addcmul``, ``add(alpha=dt)``); in
  bf16 on a GPU the output and down projections write float32 themselves
  (``torch.mm(out_dtype=float32)``, :meth:`Fused.project_out`): the residual sum then reads one
  dtype (PyTorch's elementwise kernels on mixed dtypes are not vectorised: the expert's 360 gated
  residuals a pass took 5.6 µs each on an H200, the rotation's single-dtype ``addcmul`` of the
  same size 3.3) and the product reaches the float32 stream unrounded;
- **Triton kernels on a GPU** (:mod:`~lerobot_armory.acceleration.triton_kernels`,
  ``hand_kernels``): the MLP's activation on the gate/up product's two halves where they lie
  (GELU and its product: two kernels, both non-vectorised on strided halves), and each residual
  sum with the norm after it and its cast (three kernels): attention's with the MLP's norm, and
  the MLP's with the next layer's input norm (a layer leaves that sum pending, :data:`Pending`,
  and the next adds it in :meth:`LeRobotOrder.enter`): −914 launches a sample in bf16, −564 in
  float32, at full depth (350 norm kernels: 17 + 17 in the VLM, 180 + 170 in the expert, each
  saving two launches in bf16, one in float32; 197 activation kernels, each saving one, two in
  the VLM, whose MLP otherwise runs two products); since 2026-11-28 #11 also the rotary
  embedding (four kernels a layer → one, writing q and the cache) and attention's mask with its
  softmax (two → one): −(198 × 3 + 197) = −791 more; off on a CPU, inside a compiled layer (inductor
  fuses those operations; between compiled layers they run) or where the device cannot run them
  (:func:`~lerobot_armory.acceleration.triton_kernels.hand_kernels_reason`);
- **K/V caches a multiple of 8 positions long** (:meth:`Fused.cache_length`): a row of scores is
  as long as the cache, and rows not 16 bytes apart keep cuBLAS off its Hopper kernels (π0.5's
  50-action suffix made every expert attention's rows 2 mod 8 long); the positions between prefix
  and suffix are zeroed once a sample (one small kernel a layer) and masked;
- **bfloat16 where it is cheap, float32 where it is free**: the residual stream stays float32
  (:meth:`Fused.stream`): the norms read it as it is and round once, as they hand the projections
  their bf16 input (LeRobot casts the bf16 stream to float32 before every norm, and rounds every
  residual sum to bf16); attention scores, mask and softmax stay in bf16 (softmax computes in
  float32 inside either way; LeRobot's float32 mask makes its scores and probabilities float32,
  then casts them back; the Triton kernel adds the mask in float32 too). The weights stay as LeRobot loads them.

Numerics: in float32, the same operations with a different rounding order (a fused ``a + b·c``
rounds once where two kernels round twice, the fused norm reduces in its own order, the shift
is summed inside the matrix product): ``tests/policies/test_pi05_static.py`` holds the fused
chunks to LeRobot's within 1e-5. Folding the scale into q is exact when it is a power of two
(π0.5's head size 256 gives 1/16). In bfloat16 the float32 residual stream is what matters: the
fused chunks are nearer a float32 model's than LeRobot's own bf16 chunks (on a GPU the output and
down projections' products reach the stream unrounded too: :meth:`Fused.project_out`), by how much depends on
how much the bf16 products weigh against the stream's rounding: 0.07–0.09× LeRobot's distance on a
random-weight π0.5 (whose small expert gates damp the products), 0.3–0.5× with its gates raised
to ≈ 1, 0.6–1.3× on π0 (no gates: within noise of LeRobot's), on the CPU (``benchmarks/bf16_accuracy.py``,
``docs/results/pi05_static``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from lerobot.policies.pi_gemma import _gated_residual
from torch import Tensor

from lerobot_armory.acceleration.triton_kernels import (
    LayerShape,
    add_rms_norm,
    attention_kernels_reason,
    gelu_tanh_mul,
    hand_kernels_reason,
    masked_softmax,
    rope_qkv,
)


# A layer's last residual sum, left for the next layer to add with its input norm (LeRobotOrder.enter):
# the MLP's output and its gate (None: none), or None where no layer came before.
Pending = tuple[Tensor, Tensor | None] | None

# Fused K/V caches hold a multiple of this many positions (Fused.cache_length): 16 bytes of bf16.
KEY_ALIGN = 8


def float32_products_reason(device: torch.device, dtype: torch.dtype) -> str | None:
    """Why :class:`Fused` cannot write the output and down projections in float32 on ``device``
    for weights of ``dtype`` (None: it can; tried once on the device)."""
    if dtype != torch.bfloat16:
        return f"the projections are {dtype}, not bf16"
    if device.type != "cuda":
        return "torch.mm(out_dtype=float32) runs on CUDA only"
    if torch.cuda.is_current_stream_capturing():  # never launch a probe into someone's graph
        return "a CUDA graph was being recorded when the sampler was built"
    try:
        probe = torch.ones(KEY_ALIGN, KEY_ALIGN, dtype=dtype, device=device)
        out = _float32_mm(probe, probe)
    except torch.cuda.OutOfMemoryError:
        raise  # not an answer about the product: the load fails as it would have anyway
    except (RuntimeError, TypeError, NotImplementedError) as exc:  # an older torch, a device without it
        return f"torch.mm(out_dtype=float32) failed: {str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__}"
    if out.dtype != torch.float32:
        return f"torch.mm(out_dtype=float32) gave {out.dtype}"
    return None


def _float32_mm(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` of bf16 matrices, written in float32 by the product (CUDA only)."""
    return torch.mm(a, b, out_dtype=torch.float32)


def key_aligned(length: int) -> int:
    """``length`` positions rounded up to a multiple of :data:`KEY_ALIGN`."""
    return -(-length // KEY_ALIGN) * KEY_ALIGN

# Buffers Fused registers on LeRobot's modules (non-persistent: never in a state dict).
_QKV, _GATE_UP, _NORM = "armory_qkv_weight", "armory_gate_up_weight", "armory_weight"


@dataclass(frozen=True)
class Modulation:
    """One adaptive RMSNorm's time conditioning at one flow step (LeRobot's ``PiGemmaRMSNorm``
    given ``cond``): ``normed · scale1 + shift``, then ``gate`` on the residual after the layer
    part it feeds. Made once per policy (every batch row shares the flow time: one row broadcasts)."""

    scale1: Tensor  # 1 + scale, float32 (1, 1, W); (W,) once folded
    shift: Tensor | None  # float32 (1, 1, W); None once folded into ``bias``
    gate: Tensor  # in the expert's dtype (1, 1, W); float32 once folded with float32 products
    bias: Tensor | None = None  # the next projection's weight times ``shift`` (:meth:`Fused.fold`)


class LeRobotOrder:
    """LeRobot's and HF's operations, in their order (see the module docstring).

    Layouts: rotary tables ``(B, 1, L, d)``; masks ``(B, 1, Lq, Lk)``; q/k/v ``(B, heads, L, d)``;
    keys and values (:meth:`qkv`'s, and a K/V cache's) a pair ``(k, v)``.
    """

    def __init__(self, attention: str) -> None:
        self.attention = attention

    def rope(self, text_model: Any, x: Tensor, positions: Tensor) -> tuple[Tensor, Tensor]:
        """The model's rotary table for ``positions``, with the sign of ``rotate_half`` folded into
        the sine: ``rotate_half(q) · sin`` is then ``swap_halves(q) · signed_sin``, bit for bit."""
        cos, sin = text_model.rotary_emb(x, positions)
        return cos.unsqueeze(1), _signed(sin).unsqueeze(1)

    @staticmethod
    def mask(additive: Tensor, dtype: torch.dtype) -> Tensor:
        """``(B, Lq, Lk)`` additive mask in this layout, for scores of ``dtype`` (LeRobot keeps its
        mask in float32: bfloat16 scores plus it are float32 scores)."""
        return additive[:, None]

    @staticmethod
    def stream(x: Tensor, dtype: torch.dtype) -> Tensor:
        """The residual stream's start: LeRobot's is in the layers' dtype."""
        return x.to(dtype)

    @staticmethod
    def fold(mod: Modulation, into: Any) -> Modulation:
        """``mod`` as :meth:`ada_norm` takes it before the projections of ``into`` (a layer's
        attention or MLP): LeRobot's order folds nothing."""
        return mod

    @staticmethod
    def norm(norm: Any, h: Tensor) -> Tensor:
        return norm(h, cond=None)[0]

    @staticmethod
    def final_norm(norm: Any, h: Tensor) -> Tensor:
        """A model's last plain norm (π0's expert, before its float32 action projection)."""
        return norm(h, cond=None)[0]

    @staticmethod
    def ada_norm(norm: Any, h: Tensor, mod: Modulation) -> Tensor:
        """``PiGemmaRMSNorm.forward(h, cond)`` with the conditioning precomputed."""
        assert mod.shift is not None
        return (norm._norm(h) * mod.scale1 + mod.shift).to(h.dtype)

    @staticmethod
    def cache_length(prefix: int, suffix: int) -> int:
        """Positions a K/V cache holds for a prefix and a suffix: LeRobot's, the two end to end."""
        return prefix + suffix

    def new_cache(self, attn: Any, x: Tensor, prefix: int, suffix: int) -> Any:
        """An empty K/V cache for the rows of ``x`` (the layer's input): :meth:`cache_length`
        positions, the prefix's first, the suffix's last."""
        shape = (x.shape[0], attn.config.num_key_value_heads, self.cache_length(prefix, suffix), attn.head_dim)
        return x.new_empty(shape), x.new_empty(shape)

    @staticmethod
    def cached(cache: Any, length: int) -> Any:
        """The keys and values of the first ``length`` positions (a view)."""
        return cache[0][:, :, :length], cache[1][:, :, :length]

    @staticmethod
    def length(cache: Any) -> int:
        """Positions the cache holds."""
        return cache[0].shape[2]

    @staticmethod
    def qkv(attn: Any, x: Tensor, rope: tuple[Tensor, Tensor], cache: Any, start: int, bias: Tensor | None = None) -> Tensor:
        """Projections and HF's ``apply_rotary_pos_emb``; keys and values written into ``cache`` from
        position ``start`` on, in place (HF's cache concatenates a copy); returns q ``(B, heads, L, d)``."""
        assert bias is None  # fold() folds nothing here
        cos, signed_sin = rope
        shape = (*x.shape[:-1], -1, attn.head_dim)
        q = attn.q_proj(x).view(shape).transpose(1, 2)
        k = attn.k_proj(x).view(shape).transpose(1, 2)
        v = attn.v_proj(x).view(shape).transpose(1, 2)
        end = start + x.shape[1]
        cache[0][:, :, start:end] = k * cos + _swap_halves(k) * signed_sin
        cache[1][:, :, start:end] = v
        return q * cos + _swap_halves(q) * signed_sin

    def attend(self, attn: Any, q: Tensor, kv: Any, mask: Tensor) -> Tensor:
        """Attention of ``q`` (B, Hq, Lq, d) over the pair ``kv`` (B, Hkv, Lk, d); returns (B, Lq, Hq·d)."""
        return _attention(self.attention, q, kv[0], kv[1], mask, attn.scaling)

    @staticmethod
    def project_out(linear: Any, x: Tensor) -> Tensor:
        """A layer part's last projection (attention's output, the MLP's down)."""
        return linear(x)

    def residual_norm(self, h: Tensor, y: Tensor, gate: Tensor | None, norm: Any, mod: Modulation | None) -> tuple[Tensor, Tensor]:
        """A residual sum and the norm after it (attention's, before the MLP; the MLP's, before
        the next layer): ``(h + y · gate, the norm of it)``, the norm adaptive when ``mod`` is given."""
        h = self.residual(h, y, gate)
        return h, self.norm(norm, h) if mod is None else self.ada_norm(norm, h, mod)

    def enter(self, h: Tensor, pending: Pending, norm: Any, mod: Modulation | None) -> tuple[Tensor, Tensor]:
        """A layer's input norm, after the residual sum the layer before left ``pending`` (its
        MLP's output and gate; None: the first layer), so that the two can be one kernel
        (:meth:`residual_norm`). Returns the stream and the normed input."""
        if pending is None:
            return h, self.norm(norm, h) if mod is None else self.ada_norm(norm, h, mod)
        return self.residual_norm(h, pending[0], pending[1], norm, mod)

    @staticmethod
    def residual(h: Tensor, y: Tensor, gate: Tensor | None) -> Tensor:
        return _gated_residual(h, y, gate)

    @staticmethod
    def mlp(mlp: Any, x: Tensor, bias: Tensor | None = None, apart: bool = False) -> Tensor:
        """The MLP (``apart``: gate and up as two products, which LeRobot's always are)."""
        assert bias is None  # fold() folds nothing here
        return mlp(x)

    @staticmethod
    def euler(x: Tensor, v: Tensor, dt: float) -> Tensor:
        return x + dt * v


class Fused(LeRobotOrder):
    """The same values as :class:`LeRobotOrder` with fewer kernels (see the module docstring).

    Layouts: rotary tables ``(B, L, Hq + 2·Hkv, d)`` with q's scale in and v's rows the identity;
    masks ``(B, Lq, 1, Lk)``; q ``(B, Lq, Hq, d)``; keys and values one tensor ``(B, L, 2·Hkv, d)``
    (k's heads, then v's), as the projection lays them out and the K/V cache holds them.

    Args:
        text_models: the Gemma models whose layers run here (the VLM and the action expert);
            their layers' projection weights become views of fused tensors (:func:`fuse_weights`).
        attention: ``eager`` or ``sdpa``.

    Raises:
        ValueError: a layer cannot be fused (:func:`fusable_reason`).
    """

    # The rotary embedding and attention's mask + softmax in Triton too, where the kernels run
    # (``gpu_profile``'s ``-notritonattention`` patches this to measure them against PyTorch's).
    triton_attention = True

    def __init__(self, text_models: list[Any], attention: str) -> None:
        super().__init__(attention)
        why = fusable_reason(text_models)
        if why is not None:
            raise ValueError(why)
        # The fused weights live on LeRobot's modules as non-persistent buffers (not in a state
        # dict, not saved), so a compiled layer (:meth:`StaticPi05.compile_layers`) reads each
        # layer's own: torch.compile lifts a module's buffers as inputs, where a dict keyed by
        # module would hand every layer the first one's.
        self.compute_dtype = text_models[0].layers[0].self_attn.q_proj.weight.dtype  # the projections' (fusable_reason: one)
        device = text_models[0].layers[0].self_attn.q_proj.weight.device
        # Output and down projections written in float32 (project_out), where the device can.
        self.float32_products_reason = float32_products_reason(device, self.compute_dtype)
        self.float32_products = self.float32_products_reason is None
        # The Triton kernels (triton_kernels.py) for the MLP's activation and the residual + norm,
        # where the device runs them and every MLP's activation is the tanh GELU they compute.
        residual_dtype = torch.float32 if self.float32_products else self.compute_dtype  # the products' and gates'
        shapes = [_layer_shape(model) for model in text_models]
        self.hand_kernels_reason = _tanh_gelu_reason(text_models) or hand_kernels_reason(device, self.compute_dtype, residual_dtype, shapes)
        self.hand_kernels = self.hand_kernels_reason is None
        if not self.triton_attention:
            self.attention_kernels_reason: str | None = "turned off (Fused.triton_attention)"
        else:
            self.attention_kernels_reason = self.hand_kernels_reason or attention_kernels_reason(device, self.compute_dtype, shapes)
        self.attention_kernels = self.attention_kernels_reason is None
        self.rope_scale: dict[Any, tuple[Tensor, Tensor]] = {}  # per model, each (Hq + 2·Hkv, 1): the scale, cos's offset
        for model in text_models:
            attn = model.layers[0].self_attn
            heads, kv_heads = _heads(attn)
            weight = attn.q_proj.weight
            # In the dtype of the model's rotary table (its hidden states'), made here: a tensor
            # filled from Python inside a recorded region would be a host-to-device copy.
            # q's rows scaled, k's rotated, v's unrotated (cos 1, sin 0: v · 1 + swap(v) · 0 is v,
            # bit for bit), so one rotation serves q, k and v and writes the keys and values
            # side by side straight into the cache.
            scale = torch.ones(heads + 2 * kv_heads, 1, device=weight.device)
            scale[:heads] = attn.scaling
            scale[heads + kv_heads :] = 0.0
            offset = torch.zeros_like(scale)
            offset[heads + kv_heads :] = 1.0
            table_dtype = weight.dtype if weight.dtype == torch.bfloat16 else torch.float32
            self.rope_scale[model] = (scale.to(table_dtype), offset.to(table_dtype))
            for layer in model.layers:
                attn, mlp = layer.self_attn, layer.mlp
                attn.register_buffer(_QKV, fuse_weights([attn.q_proj, attn.k_proj, attn.v_proj]), persistent=False)
                mlp.register_buffer(_GATE_UP, fuse_weights([mlp.gate_proj, mlp.up_proj]), persistent=False)
            for norm in (*(n for lay in model.layers for n in (lay.input_layernorm, lay.post_attention_layernorm)), model.norm):
                if getattr(norm, "dense", None) is None:  # a plain Gemma norm: LeRobot multiplies by 1 + weight
                    norm.register_buffer(_NORM, 1.0 + norm.weight.detach().float(), persistent=False)

    @staticmethod
    def qkv_weight(attn: Any) -> Tensor:
        """The layer's q, k and v weights as one tensor (theirs are views of it)."""
        return getattr(attn, _QKV)

    @staticmethod
    def gate_up_weight(mlp: Any) -> Tensor:
        """The MLP's gate and up weights as one tensor (theirs are views of it)."""
        return getattr(mlp, _GATE_UP)

    def rope(self, text_model: Any, x: Tensor, positions: Tensor) -> tuple[Tensor, Tensor]:
        """One table for q's, k's and v's heads side by side: q's rows times the attention scale
        (rotation is linear: scaling q's rotated value is scaling q), v's the identity."""
        cos, sin = text_model.rotary_emb(x, positions)
        scale, offset = (t.to(cos.dtype) for t in self.rope_scale[text_model])  # no-ops: made in the table's dtype
        # cos · scale + offset: q's and k's rows exactly cos · scale (0 added), v's exactly 1; sin · scale: v's 0.
        return torch.addcmul(offset, cos[:, :, None, :], scale), _signed(sin)[:, :, None, :] * scale

    @staticmethod
    def mask(additive: Tensor, dtype: torch.dtype) -> Tensor:
        """In the scores' dtype, made once a sample: a masked score is then as negative as softmax
        needs (exp gives 0 either way) and an attended one is added 0, exactly as in float32."""
        return additive[:, :, None].to(dtype)

    @staticmethod
    def stream(x: Tensor, dtype: torch.dtype) -> Tensor:
        """The residual stream's start, in float32 whatever the layers' dtype: each norm then reads
        it as it is (LeRobot's bf16 layers cast it to float32 before every norm, one kernel each)
        and each residual sum is stored unrounded (LeRobot rounds it to bf16 once a layer part)."""
        return x.float()

    def fold(self, mod: Modulation, into: Any) -> Modulation:
        """The conditioning of the norm before ``into``'s projections (a layer's attention or MLP),
        folded where it costs no kernel: ``scale1`` becomes the norm's weight (one ``rms_norm``)
        and ``shift`` the projection's bias, ``W · shift`` (a bias in the matrix product's
        epilogue), so ``W(normed · scale1 + shift)`` is ``W(normed · scale1) + W · shift``."""
        weight = getattr(into, _QKV, None)
        weight = getattr(into, _GATE_UP) if weight is None else weight
        assert mod.shift is not None
        with torch.no_grad():
            bias = torch.nn.functional.linear(mod.shift.reshape(-1), weight.float()).to(weight.dtype)
        # With float32 products the residual reads float32 only: LeRobot's bf16 gate, in float32.
        gate = mod.gate.float() if self.float32_products else mod.gate
        return Modulation(mod.scale1.reshape(-1), None, gate, bias)

    def norm(self, norm: Any, h: Tensor) -> Tensor:
        """On the float32 stream, in one kernel, rounded to the layers' dtype for the projections."""
        return self.final_norm(norm, h).to(self.compute_dtype)

    @staticmethod
    def final_norm(norm: Any, h: Tensor) -> Tensor:
        """On the float32 stream, in one kernel, left in float32 (LeRobot rounds it to the layers'
        dtype, then casts it back to float32 for the action projection)."""
        return torch.nn.functional.rms_norm(h, (h.shape[-1],), getattr(norm, _NORM), norm.eps)

    def ada_norm(self, norm: Any, h: Tensor, mod: Modulation) -> Tensor:
        """Folded (:meth:`fold`): ``normed · scale1`` in one kernel, the shift left to the next
        projection's bias. Not folded (the final norm, before LeRobot's float32 action
        projection): the whole ``normed · scale1 + shift`` in float32."""
        if mod.shift is None:
            return torch.nn.functional.rms_norm(h, (h.shape[-1],), mod.scale1, norm.eps).to(self.compute_dtype)
        return torch.addcmul(mod.shift, torch.nn.functional.rms_norm(h, (h.shape[-1],), None, norm.eps), mod.scale1)

    @staticmethod
    def cache_length(prefix: int, suffix: int) -> int:
        """The two end to end, rounded up to a multiple of :data:`KEY_ALIGN` positions: a row of
        attention scores (and of probabilities, the left operand of the product with the values)
        is as long as the cache, and a matrix whose rows are not 16 bytes apart keeps cuBLAS off
        Hopper's fast kernels (TMA needs 16-byte strides). π0.5's suffix is 50 positions and its
        prefix a multiple of 8 (256 per camera, prompt buckets 64/128/200), so every expert
        attention had rows 2 mod 8 long: on an H200 its 360 products a sample ran in Ampere's
        ``align2`` kernels, 2.6 ms at b = 1 and 5.0 ms at b = 8. The positions between prefix and
        suffix are zero and masked: they add nothing to any row."""
        return key_aligned(prefix + suffix)

    def new_cache(self, attn: Any, x: Tensor, prefix: int, suffix: int) -> Tensor:
        """An empty K/V cache, the positions between prefix and suffix zeroed (never written,
        masked: an unset key could be NaN, and a NaN score stays NaN however masked)."""
        length = self.cache_length(prefix, suffix)
        cache = x.new_empty(x.shape[0], length, 2 * attn.config.num_key_value_heads, attn.head_dim)
        if length > prefix + suffix:
            cache[:, prefix : length - suffix].zero_()
        return cache

    @staticmethod
    def cached(cache: Tensor, length: int) -> Tensor:
        return cache[:, :length]

    @staticmethod
    def length(cache: Tensor) -> int:
        return cache.shape[1]

    def qkv(self, attn: Any, x: Tensor, rope: tuple[Tensor, Tensor], cache: Tensor, start: int, bias: Tensor | None = None) -> Tensor:
        """One projection (``bias``: a folded shift), one rotation for q, k and v; the rotation's
        last kernel runs twice, once for q's rows (a fresh contiguous q, the layout attention
        gathers its rows in) and once for k's and v's, stored straight into ``cache``: no copy.
        Where the Triton kernels run, the whole rotation is one kernel writing both."""
        heads, kv_heads = _heads(attn)
        qkv = torch.nn.functional.linear(x, self.qkv_weight(attn), bias).view(*x.shape[:-1], heads + 2 * kv_heads, attn.head_dim)
        cos, signed_sin = rope
        dest = cache[:, start : start + x.shape[1]]
        if self.attention_kernels and self.triton_here():  # one kernel for the four below
            return rope_qkv(qkv, cos, signed_sin, heads, dest)
        rotated, swapped = qkv * cos, _swap_halves(qkv)  # q scaled, k rotated, v as it was (after the addcmul)
        kv = (rotated[:, :, heads:], swapped[:, :, heads:], signed_sin[:, :, heads:])
        if torch.compiler.is_compiling():
            # Dynamo refuses an ``out=`` that is not contiguous (a graph break); inductor fuses
            # the copy into the addcmul's kernel anyway.
            dest.copy_(torch.addcmul(*kv))
        else:
            torch.addcmul(*kv, out=dest)
        return torch.addcmul(rotated[:, :, :heads], swapped[:, :, :heads], signed_sin[:, :, :heads])

    def attend(self, attn: Any, q: Tensor, kv: Tensor, mask: Tensor) -> Tensor:
        """``q`` (B, Lq, Hq, d), scaled; ``kv`` (B, Lk, 2·Hkv, d); ``mask`` (B, Lq, 1, Lk)."""
        b, lq, heads, d = q.shape
        kv_heads = kv.shape[2] // 2
        if self.attention == "sdpa" or kv_heads != 1:
            k, v = kv[:, :, :kv_heads].transpose(1, 2), kv[:, :, kv_heads:].transpose(1, 2)
            return _attention(self.attention, q.transpose(1, 2), k, v, mask.transpose(1, 2), 1.0)
        # One K/V head: every query row (token, head) attends the same keys, so the rows stay in
        # the projection's order and the output needs no transpose. k and v are read where they
        # lie (rows 2·d apart): the matrix products take the stride, no copy.
        # (``baddbmm`` would not save the mask's kernel: on CUDA it copies its input into the output
        # before the product, a kernel the op count does not see.)
        scores = torch.bmm(q.reshape(b, lq * heads, d), kv[:, :, 0].transpose(1, 2)).view(b, lq, heads, -1)
        # In the scores' own dtype (the mask is made in it): softmax computes in float32 inside
        # and rounds each probability once as it stores it, where LeRobot's float32 scores, float32
        # probabilities and a cast read and write the largest tensor of the layer three more times
        # (same values: the added mask is 0 or beyond exp's range either way).
        # (The Triton kernel adds the mask in float32 and rounds each probability once too; one
        # kernel, where PyTorch's add reads the mask broadcast over heads, non-vectorised.)
        probs = masked_softmax(scores, mask) if self.attention_kernels and self.triton_here() else torch.nn.functional.softmax(scores.add_(mask), dim=-1)
        return torch.bmm(probs.view(b, lq * heads, -1), kv[:, :, 1]).view(b, lq, heads * d)

    def project_out(self, linear: Any, x: Tensor) -> Tensor:
        """In float32, written by the product itself, where the device can (``float32_products``):
        the residual sum after it then reads one dtype (see the module docstring)."""
        if not self.float32_products or type(linear) is not torch.nn.Linear or linear.bias is not None or x.dtype != linear.weight.dtype:
            return linear(x)
        return _float32_mm(x.reshape(-1, x.shape[-1]), linear.weight.t()).view(*x.shape[:-1], linear.weight.shape[0])

    @staticmethod
    def residual(h: Tensor, y: Tensor, gate: Tensor | None) -> Tensor:
        return h + y if gate is None else torch.addcmul(h, y, gate)

    def residual_norm(self, h: Tensor, y: Tensor, gate: Tensor | None, norm: Any, mod: Modulation | None) -> tuple[Tensor, Tensor]:
        """One Triton kernel where it runs (``hand_kernels``, outside a compiled graph, where
        inductor fuses PyTorch's operations itself), three of PyTorch's otherwise."""
        if not self.triton_here() or (mod is not None and mod.shift is not None):
            return super().residual_norm(h, y, gate, norm, mod)
        weight = getattr(norm, _NORM) if mod is None else mod.scale1
        return add_rms_norm(h, y, gate, weight, norm.eps, self.compute_dtype)

    def triton_here(self) -> bool:
        """Whether the Triton kernels run at this point: ``hand_kernels``, and not inside a graph
        torch.compile is tracing (inductor fuses the same operations; an opaque kernel would stand
        between its fusions), so a compiled sampler keeps them between its compiled layers."""
        return self.hand_kernels and not torch.compiler.is_compiling()

    def mlp(self, mlp: Any, x: Tensor, bias: Tensor | None = None, apart: bool = False) -> Tensor:
        """The MLP, its gate and up one product (``apart``: two, for many rows; see the module
        docstring), the activation one Triton kernel where it runs (``hand_kernels``: it reads the
        product's halves where they lie, so ``apart`` is moot)."""
        if self.triton_here():
            gate_up = torch.nn.functional.linear(x, self.gate_up_weight(mlp), bias)
            return self.project_out(mlp.down_proj, gelu_tanh_mul(gate_up))
        gate, up = self.gate_up(mlp, x, bias, apart)
        return self.project_out(mlp.down_proj, mlp.act_fn(gate) * up)

    def gate_up(self, mlp: Any, x: Tensor, bias: Tensor | None, apart: bool) -> tuple[Tensor, Tensor]:
        """The MLP's gate and up outputs: halves of one product, or (``apart``) two contiguous
        products, whose weights are the two halves of the fused one."""
        weight = self.gate_up_weight(mlp)
        if not apart:
            return torch.nn.functional.linear(x, weight, bias).chunk(2, dim=-1)
        half = weight.shape[0] // 2
        gate_bias, up_bias = (None, None) if bias is None else (bias[:half], bias[half:])
        return torch.nn.functional.linear(x, weight[:half], gate_bias), torch.nn.functional.linear(x, weight[half:], up_bias)

    @staticmethod
    def euler(x: Tensor, v: Tensor, dt: float) -> Tensor:
        return torch.add(x, v, alpha=dt)


def _tanh_gelu_reason(text_models: list[Any]) -> str | None:
    """Why the MLPs' activation is not the tanh GELU the Triton kernel computes (None: it is),
    judged by what each computes on a few values."""
    probe = torch.linspace(-6.0, 6.0, 97)
    want = torch.nn.functional.gelu(probe, approximate="tanh")
    for model in text_models:
        with torch.no_grad():
            got = model.layers[0].mlp.act_fn(probe)
        if not torch.allclose(got, want, atol=1e-6, rtol=0):
            return f"{type(model).__name__}'s MLP activation is not the tanh GELU"
    return None


def fuse_weights(linears: list[Any]) -> Tensor:
    """One weight for ``linears`` stacked by output rows; each module's weight becomes a view of
    it (same values, no second copy). The linears must pass :func:`unfusable`.

    Side effects on the policy, which a server never meets: safetensors refuses to save a weight
    that is a view of a larger tensor (``save_pretrained`` after fusing fails), and a ``.to()``
    after fusing gives the modules new weights while a sampler keeps the fused tensor it made."""
    weights = [lin.weight for lin in linears]
    with torch.no_grad():
        fused = _fused_already(weights)
        if fused is not None:  # a second sampler over the same policy: share the first's tensor
            return fused
        fused = torch.cat([w.detach() for w in weights])
        start = 0
        for w in weights:
            w.data = fused[start : start + w.shape[0]]
            start += w.shape[0]
    return fused


def _fused_already(weights: list[Tensor]) -> Tensor | None:
    """The tensor ``weights`` are consecutive views of, covering all of it (None: they are not)."""
    storage = weights[0].untyped_storage()
    offset = 0
    for w in weights:
        if w.untyped_storage().data_ptr() != storage.data_ptr() or w.storage_offset() != offset or not w.is_contiguous():
            return None
        offset += w.numel()
    if offset * weights[0].element_size() != storage.nbytes():
        return None
    rows = sum(w.shape[0] for w in weights)
    return torch.empty(0, dtype=weights[0].dtype, device=weights[0].device).set_(storage, 0, (rows, weights[0].shape[1]))


def fusable_reason(text_models: list[Any]) -> str | None:
    """Why :class:`Fused` cannot run these models' layers (None: it can)."""
    if len({layer.self_attn.q_proj.weight.dtype for model in text_models for layer in model.layers}) > 1:
        return "the layers' projections are in more than one dtype"
    for model in text_models:
        for layer in model.layers:
            attn, mlp = layer.self_attn, layer.mlp
            for group in ((attn.q_proj, attn.k_proj, attn.v_proj), (mlp.gate_proj, mlp.up_proj)):
                why = unfusable(group)
                if why is not None:
                    return why
    return None


def unfusable(linears: Any) -> str | None:
    """Why these linears cannot share one weight (None: they can)."""
    if any(getattr(lin, "bias", None) is not None for lin in linears):
        return "a projection has a bias"
    if len({(lin.weight.dtype, lin.weight.device, lin.weight.shape[1]) for lin in linears}) != 1:
        return "a layer's projections differ in dtype, device or input width"
    return None


def _attention(kind: str, q: Tensor, k: Tensor, v: Tensor, mask: Tensor, scaling: float) -> Tensor:
    """Attention of ``q`` (B, Hq, Lq, d) over ``k``/``v`` (B, Hkv, Lk, d) with an additive ``mask``
    (B, 1, Lq, Lk); returns (B, Lq, Hq·d)."""
    b, heads, lq, d = q.shape
    groups = heads // k.shape[1]
    if kind == "sdpa":
        out = torch.nn.functional.scaled_dot_product_attention(q, k, v, attn_mask=mask.to(q.dtype), scale=scaling, enable_gqa=groups > 1)
    else:
        # HF's eager_attention_forward, with the query heads of one K/V head folded into the
        # query length instead of the K/V head copied ``groups`` times (repeat_kv).
        qg = q.reshape(b, k.shape[1], groups * lq, d)
        scores = torch.matmul(qg, k.transpose(2, 3))
        if scaling != 1.0:
            scores = scores * scaling
        scores = scores.view(b, heads, lq, -1) + mask
        probs = torch.nn.functional.softmax(scores, dim=-1, dtype=torch.float32).to(q.dtype)
        out = torch.matmul(probs.view(b, k.shape[1], groups * lq, -1), v).view(b, heads, lq, d)
    return out.transpose(1, 2).reshape(b, lq, heads * d)


def _layer_shape(model: Any) -> LayerShape:
    """What the Triton kernels see of ``model``'s layers (all alike: :func:`fusable_reason`)."""
    layer = model.layers[0]
    heads, kv_heads = _heads(layer.self_attn)
    width, mlp_width = layer.mlp.gate_proj.weight.shape[::-1]
    return LayerShape(width, mlp_width, heads, kv_heads, layer.self_attn.head_dim)


def _heads(attn: Any) -> tuple[int, int]:
    return attn.config.num_attention_heads, attn.config.num_key_value_heads


def _signed(sin: Tensor) -> Tensor:
    half = sin.shape[-1] // 2
    return torch.cat((-sin[..., :half], sin[..., half:]), dim=-1)


def _swap_halves(x: Tensor) -> Tensor:
    half = x.shape[-1] // 2
    return torch.cat((x[..., half:], x[..., :half]), dim=-1)
