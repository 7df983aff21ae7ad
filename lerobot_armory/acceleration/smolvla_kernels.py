"""SmolVLA's Llama layers as :class:`~.smolvla_static.StaticSmolVLA` runs them: with fewer kernels
(:class:`SmolVLAFused`, the default) or in LeRobot's own order (:class:`SmolVLAOrdered`), one
interface, so the sampler has one loop.

LeRobot's SmolVLA runs HF's Llama layers through its own helpers, and a CPU trace of the narrow
SmolVLA (SmolVLM2-500M's depths) counts ≈ 57 kernels per action-expert layer and step, 16 layers
at each of 10 steps: its ``apply_rope`` rebuilds the rotary frequencies (arange, pow, divide, sine,
cosine) at every call, a Llama RMSNorm is six kernels, and ``eager_attention_forward`` copies the
keys and values once per query head (the expand and reshape of grouped-query attention), casts
them and masks with ``torch.where``. :class:`SmolVLAFused` computes the same values with ≈ 20:

- **one projection for q, k and v, and one for the MLP's gate and up**: the layer's weights become
  views of one concatenated tensor (``pi05_kernels.fuse_weights``: nothing copied, LeRobot's
  modules keep working on them);
- **RMSNorm as one kernel** (``torch.nn.functional.rms_norm``: ``_fused_rms_norm`` on CUDA);
- **the rotary tables made once a sample** (prefix positions, the suffix's, the cross-attention
  queries'), with the attention scale folded into q's rows, and **q and k rotated together**
  (three kernels, LeRobot's formula: ``x1·cos − x2·sin``, ``x2·cos + x1·sin``);
- **the K/V caches head-major** (``(B, K/V heads, length, d)``), so grouped-query attention folds
  each K/V head's query heads into the query length and reads keys and values where they lie: one
  product for the scores, the mask added in place (additive, ``finfo.min``: the same zeros after
  softmax as LeRobot's ``where``, the same uniform row for a row that sees nothing), softmax, one
  product for the output, one copy into the output projection's layout;
- residuals without LeRobot's defensive ``clone``;
- **keys a multiple of 8 positions long**: the prefix padded as LeRobot pads it to a configured
  ``prefix_length`` (zeros, masked) and the caches rounded up (masked zeros after the suffix), so
  that attention's rows suit cuBLAS's Hopper kernels (as ``pi05_kernels.Fused.cache_length``).

Numerics: float32 scores and softmax as LeRobot's; every value is LeRobot's up to the rounding
order (a fused norm reduces in its own order, ``addcmul`` rounds once where two kernels round
twice; folding the scale into q is exact when it is a power of two — SmolVLM2's head size 64 gives
1/8): ``tests/policies/test_smolvla_static.py`` holds the fused chunks to LeRobot's within 1e-5.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from lerobot_armory.acceleration.pi05_kernels import _swap_halves, fuse_weights, key_aligned, unfusable

ROPE_WAVELENGTH = 10_000  # LeRobot's apply_rope default (SmolVLA calls it without the config's rope_theta)


def fusable_reason(vwe: Any, self_attention: list[bool]) -> str | None:
    """Why :class:`SmolVLAFused` cannot run this ``SmolVLMWithExpertModel`` (None: it can)."""
    text, expert = vwe.get_vlm_model().text_model, vwe.lm_expert
    if getattr(text.config, "hidden_act", "silu") != "silu" or getattr(expert.config, "hidden_act", "silu") != "silu":
        return "an MLP's activation is not SiLU"
    for model in (text, expert):
        for i, layer in enumerate(model.layers):
            attn, mlp = layer.self_attn, layer.mlp
            groups = [(mlp.gate_proj, mlp.up_proj)]
            if model is text or self_attention[i]:  # a cross-attention layer's q_proj runs as it is
                groups.append((attn.q_proj, attn.k_proj, attn.v_proj))
            for group in groups:
                why = unfusable(group)
                if why is not None:
                    return why
    return None


class SmolVLAFused:
    """The fused operations of every VLM and expert layer (see the module docstring).

    Args:
        vwe: LeRobot's ``SmolVLMWithExpertModel``.
        self_attention: per layer, whether the expert's layer attends the prefix's cache
            (self-attention) or its own projection of it (cross-attention).
    """

    def __init__(self, vwe: Any, self_attention: list[bool]) -> None:
        why = fusable_reason(vwe, self_attention)
        if why is not None:
            raise ValueError(why)
        self.text, self.expert = vwe.get_vlm_model().text_model, vwe.lm_expert
        self.heads, self.kv_heads = vwe.num_attention_heads, vwe.num_key_value_heads
        self.self_attention = list(self_attention)
        self.head_dim = self.text.config.head_dim
        self.scale = self.head_dim**-0.5
        # Fused weights, per layer: views of one tensor each, LeRobot's modules keep theirs as views.
        self.qkv = {}
        self.gate_up = {}
        for model in (self.text, self.expert):
            for i, layer in enumerate(model.layers):
                attn, mlp = layer.self_attn, layer.mlp
                if model is self.text or self_attention[i]:
                    self.qkv[id(layer)] = fuse_weights([attn.q_proj, attn.k_proj, attn.v_proj])
                self.gate_up[id(layer)] = fuse_weights([mlp.gate_proj, mlp.up_proj])

    # -- per sample -----------------------------------------------------------------------------

    def tables(self, positions: Tensor) -> tuple[Tensor, Tensor]:
        """Rotary tables ``(cos, signed sin)`` for ``positions`` (B, L), float32 ``(B, L, Hq + Hkv, d)``:
        q's heads scaled by the attention scale, k's not. ``x·cos + swap_halves(x)·signed_sin`` is
        LeRobot's ``apply_rope``: ``[x1·cos − x2·sin, x2·cos + x1·sin]``."""
        d_half = self.head_dim // 2
        exponents = (2.0 / self.head_dim) * torch.arange(d_half, dtype=torch.float32, device=positions.device)
        radians = positions[..., None].to(torch.float32) / (ROPE_WAVELENGTH**exponents)[None, None, :]
        sin, cos = torch.sin(radians), torch.cos(radians)
        cos = torch.cat([cos, cos], dim=-1)[:, :, None, :]
        sin = torch.cat([-sin, sin], dim=-1)[:, :, None, :]
        b, length = positions.shape

        def per_head(t: Tensor) -> Tensor:  # q's heads scaled (a Python number times a tensor: no host copy)
            return torch.cat([(t * self.scale).expand(b, length, self.heads, -1), t.expand(b, length, self.kv_heads, -1)], dim=2)

        return per_head(cos), per_head(sin)

    @staticmethod
    def additive(valid: Tensor) -> Tensor:
        """A boolean ``(B, Lq, Lk)`` pattern as float32 ``(B, 1, 1, Lq, Lk)`` to add to the scores:
        0 where a query sees a key, ``finfo.min`` where not (softmax gives exactly LeRobot's zeros,
        and a row that sees nothing the same uniform row)."""
        zero = torch.zeros((), dtype=torch.float32, device=valid.device)
        return torch.where(valid, zero, torch.finfo(torch.float32).min)[:, None, None]

    @staticmethod
    def prefix_length(length: int, lerobot_length: int) -> int:
        """The prefix's length: LeRobot's (``lerobot_length`` where its config pads to one), rounded
        up to a multiple of ``KEY_ALIGN`` with LeRobot's own padding (zero embeddings, masked), so
        that the prefix's and the cross-attention's rows of scores are 16 bytes apart, which
        cuBLAS's Hopper kernels need (SmolVLA's prefix is 64 tokens a camera, 48 of prompt and 1
        of state: 177 for two cameras, odd)."""
        return key_aligned(max(length, lerobot_length))

    @staticmethod
    def cache_length(p: int, h: int) -> int:
        """Positions a K/V cache holds for a prefix of ``p`` and a suffix of ``h``: rounded up."""
        return key_aligned(p + h)

    def caches(self, b: int, p: int, h: int, dtype: list[torch.dtype], device: torch.device) -> list[tuple[Tensor, Tensor]]:
        """Per layer, head-major keys and values ``(B, Hkv, L, d)`` in ``dtype[i]``. A layer whose
        expert attends the cache (self-attention): the prefix's ``P`` positions, the suffix's
        ``H``, then zeros (masked) up to ``L``, the next multiple of ``KEY_ALIGN``; a
        cross-attention layer's expert reads the prefix's alone: ``L = P`` (a multiple already,
        :meth:`prefix_length`)."""
        length = self.cache_length(p, h)
        out = []
        for self_attention, dt in zip(self.self_attention, dtype, strict=True):
            kv = torch.empty((2, b, self.kv_heads, length if self_attention else p, self.head_dim), dtype=dt, device=device)
            if self_attention and length > p + h:  # never written; a NaN there would stay NaN however masked
                kv[:, :, :, p + h :].zero_()
            out.append((kv[0], kv[1]))
        return out

    # -- one layer ------------------------------------------------------------------------------

    def norm(self, norm: Any, h: Tensor) -> Tensor:
        """HF's Llama RMSNorm, one kernel; a stream in another dtype than the weight (a bf16 VLM's
        first layer reads the float32 prefix) gets the weight's product after, in the promoted
        dtype, as HF's does."""
        if h.dtype == norm.weight.dtype:
            return torch.nn.functional.rms_norm(h, (h.shape[-1],), norm.weight, norm.variance_epsilon)
        return torch.nn.functional.rms_norm(h, (h.shape[-1],), eps=norm.variance_epsilon) * norm.weight

    def rotate(self, x: Tensor, table: tuple[Tensor, Tensor], heads: int) -> Tensor:
        """The first ``heads`` heads of ``x`` (B, L, ≥heads, d) rotated (and q's scaled), float32."""
        x = x[:, :, :heads].to(torch.float32)
        cos, sin = table[0][:, :, :heads], table[1][:, :, :heads]
        return torch.addcmul(x * cos, _swap_halves(x), sin)

    def self_attention_kv(self, layer: Any, x: Tensor, table: tuple[Tensor, Tensor], cache: tuple[Tensor, Tensor], start: int) -> Tensor:
        """q, k and v of ``x`` (one product), q and k rotated; k and v written into ``cache`` at
        ``start``; returns q (float32, scaled) ``(B, L, Hq, d)``."""
        heads, kv = self.heads, self.kv_heads
        qkv = torch.nn.functional.linear(x, self.qkv[id(layer)]).view(*x.shape[:-1], heads + 2 * kv, self.head_dim)
        qk = self.rotate(qkv, table, heads + kv)
        end = start + x.shape[1]
        cache[0][:, :, start:end] = qk[:, :, heads:].transpose(1, 2)
        cache[1][:, :, start:end] = qkv[:, :, heads + kv :].transpose(1, 2)
        return qk[:, :, :heads]

    @staticmethod
    def prefix_kv(cache: tuple[Tensor, Tensor], p: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """The prefix's keys and values in ``cache``, as the prefix pass attends them (read in
        place, in the cache's dtype; ``dtype`` is for :class:`SmolVLAOrdered`)."""
        return cache[0][:, :, :p], cache[1][:, :, :p]

    def cross_query(self, layer: Any, x: Tensor, table: tuple[Tensor, Tensor]) -> Tensor:
        """A cross-attention layer's q (float32, rotated and scaled) ``(B, L, Hq, d)``."""
        q = layer.self_attn.q_proj(x).view(*x.shape[:-1], self.heads, self.head_dim)
        return self.rotate(q, table, self.heads)

    def cross_kv(self, layer: Any, cache: tuple[Tensor, Tensor], p: int) -> tuple[Tensor, Tensor]:
        """A cross-attention layer's keys and values, head-major: the expert's projections of the
        VLM's prefix keys and values (once a sample)."""
        attn = layer.self_attn
        out = []
        for proj, src in ((attn.k_proj, cache[0]), (attn.v_proj, cache[1])):
            flat = src[:, :, :p].transpose(1, 2).reshape(src.shape[0], p, -1).to(proj.weight.dtype)
            out.append(proj(flat).view(src.shape[0], p, -1, self.head_dim).transpose(1, 2).contiguous())
        return out[0], out[1]

    def attend(self, q: Tensor, keys: Tensor, values: Tensor, mask: Tensor) -> Tensor:
        """Grouped-query attention: q (B, Lq, Hq, d) float32, keys/values head-major (B, Hkv, Lk, d),
        ``mask`` from :meth:`additive`; returns (B, Lq, Hq·d) in the values' dtype."""
        b, lq = q.shape[:2]
        kv, groups, lk = self.kv_heads, self.heads // self.kv_heads, keys.shape[2]
        # LeRobot's head h reads K/V head h // groups: fold each K/V head's queries into one row block.
        qg = q.view(b, lq, kv, groups, self.head_dim).permute(0, 2, 3, 1, 4).reshape(b * kv, groups * lq, self.head_dim)
        k = keys.reshape(b * kv, lk, self.head_dim).to(torch.float32)
        scores = torch.bmm(qg, k.transpose(1, 2)).view(b, kv, groups, lq, lk)
        probs = torch.softmax(scores.add_(mask), dim=-1).to(values.dtype)
        out = torch.bmm(probs.view(b * kv, groups * lq, lk), values.reshape(b * kv, lk, self.head_dim))
        return out.view(b, kv, groups, lq, self.head_dim).permute(0, 3, 1, 2, 4).reshape(b, lq, self.heads * self.head_dim)

    def rest_of_layer(self, layer: Any, h: Tensor, att: Tensor) -> Tensor:
        """Output projection, residual, norm, MLP (one gate/up product), residual; the residual
        sums in place in the projections' dtype, as LeRobot's (``out += h``)."""
        out = layer.self_attn.o_proj(att.to(layer.self_attn.o_proj.weight.dtype))
        out += h
        x = self.norm(layer.post_attention_layernorm, out)
        gate, up = torch.nn.functional.linear(x, self.gate_up[id(layer)]).chunk(2, dim=-1)
        mlp = layer.mlp.down_proj(torch.nn.functional.silu(gate) * up)
        mlp += out
        return mlp


class SmolVLAOrdered:
    """LeRobot's own operations in its order, behind :class:`SmolVLAFused`'s interface, so that
    :class:`~.smolvla_static.StaticSmolVLA` runs one loop whichever it is given: HF's modules and
    LeRobot's ``apply_rope`` / ``eager_attention_forward``, the caches ``(B, P + H, Hkv, d)`` as
    LeRobot's concatenation lays them out, a rotary "table" that is the positions themselves and a
    boolean mask. Its chunks are LeRobot's bit for bit where LeRobot's own are reproducible.

    Args:
        vwe: LeRobot's ``SmolVLMWithExpertModel``.
        text: its VLM's text model (the layers whose keys and values the caches hold).
    """

    def __init__(self, vwe: Any, text: Any) -> None:
        self.vwe, self.text = vwe, text
        self.head_dim = vwe.vlm.config.text_config.head_dim

    @staticmethod
    def tables(positions: Tensor) -> Tensor:
        return positions  # LeRobot's apply_rope takes the positions

    @staticmethod
    def additive(valid: Tensor) -> Tensor:
        return valid  # LeRobot's eager_attention_forward takes the boolean pattern

    @staticmethod
    def prefix_length(length: int, lerobot_length: int) -> int:
        """LeRobot's: padded to its config's ``prefix_length`` where that is longer."""
        return max(length, lerobot_length)

    @staticmethod
    def cache_length(p: int, h: int) -> int:
        """LeRobot's: the prefix's positions, then the suffix's."""
        return p + h

    def caches(self, b: int, p: int, h: int, dtype: list[torch.dtype], device: torch.device) -> list[tuple[Tensor, Tensor]]:
        """Per layer, keys and values ``(B, P + H, Hkv, d)`` in ``dtype[i]``."""
        out = []
        for layer, dt in zip(self.text.layers, dtype, strict=True):
            attn = layer.self_attn
            shape = (b, p + h, attn.k_proj.out_features // attn.head_dim, attn.head_dim)
            out.append((torch.empty(shape, dtype=dt, device=device), torch.empty(shape, dtype=dt, device=device)))
        return out

    @staticmethod
    def norm(norm: Any, h: Tensor) -> Tensor:
        return norm(h)

    def self_attention_kv(self, layer: Any, x: Tensor, positions: Tensor, cache: tuple[Tensor, Tensor], start: int) -> Tensor:
        """q, k and v of ``x`` (three products), q and k rotated; k and v written into ``cache``
        at ``start``; returns q ``(B, L, Hq, d)``."""
        from lerobot.policies.smolvla.smolvlm_with_expert import apply_rope

        attn = layer.self_attn
        shape = (*x.shape[:-1], -1, attn.head_dim)
        q = apply_rope(attn.q_proj(x).view(shape), positions)
        end = start + x.shape[1]
        cache[0][:, start:end] = apply_rope(attn.k_proj(x).view(shape), positions)
        cache[1][:, start:end] = attn.v_proj(x).view(shape)
        return q

    @staticmethod
    def prefix_kv(cache: tuple[Tensor, Tensor], p: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """The prefix's keys and values in the VLM's ``dtype``, as LeRobot's prefix pass attends
        them (a cache promoted for a float32 expert behind a bf16 VLM casts back exactly)."""
        return cache[0][:, :p].to(dtype), cache[1][:, :p].to(dtype)

    @staticmethod
    def cross_query(layer: Any, x: Tensor, positions: Tensor) -> Tensor:
        from lerobot.policies.smolvla.smolvlm_with_expert import apply_rope

        attn = layer.self_attn
        return apply_rope(attn.q_proj(x).view(*x.shape[:-1], -1, attn.head_dim), positions)

    @staticmethod
    def cross_kv(layer: Any, cache: tuple[Tensor, Tensor], p: int) -> tuple[Tensor, Tensor]:
        """A cross-attention layer's keys and values: the expert's projections of the VLM's prefix
        keys and values (LeRobot recomputes them at every step; they depend on the prefix alone)."""
        attn = layer.self_attn
        k, v = cache[0][:, :p], cache[1][:, :p]
        keys = attn.k_proj(k.to(dtype=attn.k_proj.weight.dtype).reshape(*k.shape[:2], -1)).view(*k.shape[:2], -1, attn.head_dim)
        values = attn.v_proj(v.to(dtype=attn.v_proj.weight.dtype).reshape(*v.shape[:2], -1)).view(*v.shape[:2], -1, attn.head_dim)
        return keys, values

    def attend(self, q: Tensor, keys: Tensor, values: Tensor, mask: Tensor) -> Tensor:
        return self.vwe.eager_attention_forward(mask, q.shape[0], self.head_dim, q, keys, values)

    @staticmethod
    def rest_of_layer(layer: Any, h: Tensor, att: Tensor) -> Tensor:
        """The output projection, residuals, norm and MLP, as ``SmolVLMWithExpertModel.forward``
        runs them after attention."""
        if att.dtype != layer.self_attn.o_proj.weight.dtype:
            att = att.to(layer.self_attn.o_proj.weight.dtype)
        out = layer.self_attn.o_proj(att)
        out += h
        after = out.clone()
        out = layer.mlp(layer.post_attention_layernorm(out))
        out += after
        return out
