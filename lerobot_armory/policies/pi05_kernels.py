"""The operations of one π0.5 transformer layer, two ways: LeRobot's own sequence, and fewer kernels.

The static sampler (``pi05_static.py``) runs the same loop either way; what differs is how many
kernels each layer launches. On a GPU under a CUDA graph the launch cost is gone but every kernel
still takes a few microseconds however small its work, and π0.5 at batch 1 is mostly small kernels:
the action expert runs 18 layers at each of 10 denoising steps. At full depth a sample launches
9,137 kernels in LeRobot's sequence and 4,536 fused in float32; 10,172 and 5,006 in bfloat16
(``benchmarks/pi05_ops.py``).

:class:`LeRobotOrder` is LeRobot's and HF's arithmetic, operation for operation (the reference:
bit for bit LeRobot's chunks on a CPU). :class:`Fused` computes the same values with fewer kernels:

- **one projection for q, k and v, and one for the MLP's gate and up** — the layer's q/k/v (and
  gate/up) weights are made *views* of one concatenated tensor (:func:`fuse_weights`): no weight
  is copied, none changes value, and LeRobot's modules keep working on them;
- **RMSNorm as one kernel** (``torch.nn.functional.rms_norm``: ``_fused_rms_norm`` on CUDA, where
  LeRobot's ``square, mean, add, rsqrt, mul`` is five), the adaptive norm's scale and shift as one
  ``addcmul``, the plain norm's ``1 + weight`` computed once;
- **the rotary embedding of q and k together, with the attention scale folded into q's table**
  (three kernels for both, where HF's is four each plus a scale on the scores); v passes the same
  three kernels unrotated (its rows of the table are cos 1, sin 0: bit for bit), so keys and values
  leave them side by side as one tensor and enter the K/V cache in **one copy**, where two were;
- **attention with one layout copy**: with one K/V head (π0.5: eight query heads on one), every
  (token, head) query row attends the same keys, so q is gathered once into ``(B, L·heads, d)``
  rows (one copy: in the fused projection each token's q heads sit beside its k and v), the
  scores, the softmax and the weighted sum run on those rows and k and v where they lie, and the
  output is the ``(B, L, heads·d)`` the output projection takes (HF transposes q and the output
  and copies K/V per query head);
- **gated residuals and the Euler step as one kernel each** (``addcmul``, ``add(alpha=dt)``).
- **bfloat16 without float32 detours it does not need**: the adaptive norm's float32 sum is
  rounded to bf16 as it is stored (``out=``, one kernel where a cast is a second), and attention
  scores, mask and softmax stay in bf16 (softmax computes in float32 inside either way; LeRobot's
  float32 mask makes its scores and probabilities float32, then casts them back).

Numerics: the same operations in float32 (or LeRobot's dtypes under bfloat16) with a different
rounding order: a fused ``a + b·c`` rounds once where two kernels round twice, the fused norm
reduces in its own order. Folding the scale into q is exact when it is a power of two (π0.5's
head size 256 gives 1/16). ``tests/policies/test_pi05_static.py`` holds the fused chunks to
LeRobot's within 1e-5 in float32. In bfloat16 the softmax's float32 sum may run in another order
than LeRobot's float32 softmax (the last bit of a probability); the chunks stay as far from a
float32 π0.5's as LeRobot's own bf16 chunks (``docs/results/pi05_static``).
"""

from __future__ import annotations

from typing import Any

import torch
from lerobot.policies.pi_gemma import _gated_residual
from torch import Tensor


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
    def norm(norm: Any, h: Tensor) -> Tensor:
        return norm(h, cond=None)[0]

    @staticmethod
    def ada_norm(norm: Any, h: Tensor, scale1: Tensor, shift: Tensor) -> Tensor:
        """``PiGemmaRMSNorm.forward(h, cond)`` with the conditioning precomputed."""
        return (norm._norm(h) * scale1 + shift).to(h.dtype)

    @staticmethod
    def qkv(attn: Any, x: Tensor, rope: tuple[Tensor, Tensor]) -> tuple[Tensor, Any]:
        """Projections and HF's ``apply_rotary_pos_emb``: q and the pair (k, v), each ``(B, heads, L, d)``."""
        cos, signed_sin = rope
        shape = (*x.shape[:-1], -1, attn.head_dim)
        q = attn.q_proj(x).view(shape).transpose(1, 2)
        k = attn.k_proj(x).view(shape).transpose(1, 2)
        v = attn.v_proj(x).view(shape).transpose(1, 2)
        return q * cos + _swap_halves(q) * signed_sin, (k * cos + _swap_halves(k) * signed_sin, v)

    @staticmethod
    def cache(kv: Any, length: int) -> Any:
        """A K/V cache of ``length`` positions holding ``kv`` (:meth:`qkv`'s) in its first ones."""
        k, v = kv
        k_buf = k.new_empty(k.shape[0], k.shape[1], length, k.shape[3])
        v_buf = v.new_empty(v.shape[0], v.shape[1], length, v.shape[3])
        k_buf[:, :, : k.shape[2]] = k
        v_buf[:, :, : v.shape[2]] = v
        return k_buf, v_buf

    @staticmethod
    def write(cache: Any, kv: Any, start: int) -> None:
        """``kv`` into ``cache`` from position ``start`` on, in place (HF's cache concatenates a copy)."""
        cache[0][:, :, start:] = kv[0]
        cache[1][:, :, start:] = kv[1]

    def attend(self, attn: Any, q: Tensor, kv: Any, mask: Tensor) -> Tensor:
        """Attention of ``q`` (B, Hq, Lq, d) over the pair ``kv`` (B, Hkv, Lk, d); returns (B, Lq, Hq·d)."""
        return _attention(self.attention, q, kv[0], kv[1], mask, attn.scaling)

    @staticmethod
    def residual(h: Tensor, y: Tensor, gate: Tensor | None) -> Tensor:
        return _gated_residual(h, y, gate)

    @staticmethod
    def mlp(mlp: Any, x: Tensor) -> Tensor:
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

    def __init__(self, text_models: list[Any], attention: str) -> None:
        super().__init__(attention)
        why = fusable_reason(text_models)
        if why is not None:
            raise ValueError(why)
        self.qkv_weight: dict[Any, Tensor] = {}
        self.gate_up_weight: dict[Any, Tensor] = {}
        self.norm_weight: dict[Any, Tensor] = {}
        self.rope_scale: dict[Any, tuple[Tensor, Tensor]] = {}  # per model, each (Hq + 2·Hkv, 1): the scale, cos's offset
        for model in text_models:
            attn = model.layers[0].self_attn
            heads, kv_heads = _heads(attn)
            weight = attn.q_proj.weight
            # In the dtype of the model's rotary table (its hidden states'), made here: a tensor
            # filled from Python inside a recorded region would be a host-to-device copy.
            # q's rows scaled, k's rotated, v's unrotated (cos 1, sin 0: v · 1 + swap(v) · 0 is v,
            # bit for bit), so one rotation serves q, k and v and the keys and values leave it
            # side by side, one copy into the cache where two were.
            scale = torch.ones(heads + 2 * kv_heads, 1, device=weight.device)
            scale[:heads] = attn.scaling
            scale[heads + kv_heads :] = 0.0
            offset = torch.zeros_like(scale)
            offset[heads + kv_heads :] = 1.0
            table_dtype = weight.dtype if weight.dtype == torch.bfloat16 else torch.float32
            self.rope_scale[model] = (scale.to(table_dtype), offset.to(table_dtype))
            for layer in model.layers:
                attn, mlp = layer.self_attn, layer.mlp
                self.qkv_weight[attn] = fuse_weights([attn.q_proj, attn.k_proj, attn.v_proj])
                self.gate_up_weight[mlp] = fuse_weights([mlp.gate_proj, mlp.up_proj])
                for norm in (layer.input_layernorm, layer.post_attention_layernorm):
                    if norm.dense is None:  # a plain Gemma norm: LeRobot multiplies by 1 + weight
                        self.norm_weight[norm] = 1.0 + norm.weight.detach().float()

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

    def norm(self, norm: Any, h: Tensor) -> Tensor:
        return torch.nn.functional.rms_norm(h.float(), (h.shape[-1],), self.norm_weight[norm], norm.eps).type_as(h)

    @staticmethod
    def ada_norm(norm: Any, h: Tensor, scale1: Tensor, shift: Tensor) -> Tensor:
        normed = torch.nn.functional.rms_norm(h.float(), (h.shape[-1],), None, norm.eps)
        # Computed in float32 and rounded to h's dtype as it is stored: one kernel where
        # ``addcmul(...).to(h.dtype)`` is two, the same rounding (one, after the sum).
        return torch.addcmul(shift, normed, scale1, out=torch.empty_like(h))

    def qkv(self, attn: Any, x: Tensor, rope: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
        heads, kv_heads = _heads(attn)
        qkv = torch.nn.functional.linear(x, self.qkv_weight[attn]).view(*x.shape[:-1], heads + 2 * kv_heads, attn.head_dim)
        cos, signed_sin = rope
        qkv = torch.addcmul(qkv * cos, _swap_halves(qkv), signed_sin)  # q scaled and rotated, k rotated, v as it was
        return qkv[:, :, :heads], qkv[:, :, heads:]

    @staticmethod
    def cache(kv: Tensor, length: int) -> Tensor:
        buf = kv.new_empty(kv.shape[0], length, *kv.shape[2:])
        buf[:, : kv.shape[1]] = kv
        return buf

    @staticmethod
    def write(cache: Tensor, kv: Tensor, start: int) -> None:
        cache[:, start:] = kv  # keys and values in one copy

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
        probs = torch.nn.functional.softmax(scores.add_(mask), dim=-1)
        return torch.bmm(probs.view(b, lq * heads, -1), kv[:, :, 1]).view(b, lq, heads * d)

    @staticmethod
    def residual(h: Tensor, y: Tensor, gate: Tensor | None) -> Tensor:
        return h + y if gate is None else torch.addcmul(h, y, gate)

    def mlp(self, mlp: Any, x: Tensor) -> Tensor:
        gate, up = torch.nn.functional.linear(x, self.gate_up_weight[mlp]).chunk(2, dim=-1)
        return mlp.down_proj(mlp.act_fn(gate) * up)

    @staticmethod
    def euler(x: Tensor, v: Tensor, dt: float) -> Tensor:
        return torch.add(x, v, alpha=dt)


def fuse_weights(linears: list[Any]) -> Tensor:
    """One weight for ``linears`` stacked by output rows; each module's weight becomes a view of
    it (same values, no second copy). The linears must pass :func:`unfusable`."""
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


def _heads(attn: Any) -> tuple[int, int]:
    return attn.config.num_attention_heads, attn.config.num_key_value_heads


def _signed(sin: Tensor) -> Tensor:
    half = sin.shape[-1] // 2
    return torch.cat((-sin[..., :half], sin[..., half:]), dim=-1)


def _swap_halves(x: Tensor) -> Tensor:
    half = x.shape[-1] // 2
    return torch.cat((x[..., half:], x[..., :half]), dim=-1)
