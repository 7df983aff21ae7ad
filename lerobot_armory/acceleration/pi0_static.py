"""The static sampler for LeRobot's π0: ``PI0Pytorch.sample_actions`` as one fixed sequence of
kernels per batch shape, like π0.5's (:mod:`.pi05_static`, which holds everything the two share:
the prefix and its K/V caches, the Euler loop, RTC, the fused kernels).

What π0 does otherwise (LeRobot 0.6.1's ``embed_suffix`` and ``denoise_step``, read there):
- its suffix starts with one **state token**, ``state_proj(state)``, before the actions; the state
  token attends the prefix and itself, the actions attend the prefix, the state and each other.
  The state's embedding is the same at every step, so it is projected once a sample (LeRobot:
  once a step); the token still passes the expert at every step, as in LeRobot;
- the flow time enters through the actions' embedding, not the norms: ``action_time_mlp_out(silu(
  action_time_mlp_in([action_in_proj(x_t), time_emb])))``. The time's half of the first product
  depends on the step alone: with the fused kernels it is computed once per policy
  (:meth:`StaticPi0.prepare`) and becomes that product's bias, ``W_a · a + (W_t · t + b)`` (one
  ``addmm``, no concatenation); in LeRobot's order the concatenation runs as LeRobot runs it;
- the expert's norms are plain Gemma norms (no adaRMS, no gates), its last one too.

Numerics as π0.5's: in float32 the chunks equal LeRobot's (``tests/policies/test_pi0_static.py``,
1e-5 at every bucket, RTC too); in bfloat16 the fused kernels keep the residual stream and the
last norm's output in float32.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from lerobot.policies.common.vla_utils import create_sinusoidal_pos_embedding
from torch import Tensor

from lerobot_armory.acceleration.pi05_kernels import Pending
from lerobot_armory.acceleration.pi05_static import SamplerInputs, StaticPi05


@dataclass(frozen=True)
class TimeEmbedding:
    """π0's flow time at one step, as its action-time MLP reads it: the sinusoidal embedding
    ``(1, 1, W)`` float32 (LeRobot's order, concatenated to every action) or, folded, the first
    product's bias ``W_t · time_emb + b`` ``(W,)``."""

    embedding: Tensor | None
    bias: Tensor | None


class StaticPi0(StaticPi05):
    """``PI0Pytorch.sample_actions`` without host synchronisation or per-step copies (arguments
    as :class:`~lerobot_armory.acceleration.pi05_static.StaticPi05`'s; its inputs carry the state,
    ``SamplerInputs.state``, padded as ``PI0Policy.prepare_state`` pads it)."""

    kind = "pi0"
    model_name = "PI0Pytorch"
    model_parts = ("action_in_proj", "action_out_proj", "state_proj", "action_time_mlp_in", "action_time_mlp_out")
    adaptive_norms = False
    takes_state = True
    state_tokens = 1

    @torch.no_grad()
    def prepare(self) -> tuple[TimeEmbedding, ...]:  # type: ignore[override]
        """Each step's time embedding, or with the fused kernels its part of the action-time MLP's
        first product (made once, outside any traced or recorded region)."""
        if self.conditioning is not None:
            return self.conditioning  # type: ignore[return-value]
        m, width = self.model, self.model.action_in_proj.out_features
        steps = []
        for step in range(self.num_steps):
            time = self.time_table[step].expand(1)
            emb = create_sinusoidal_pos_embedding(
                time, width, min_period=self.config.min_period, max_period=self.config.max_period, device=time.device
            ).type(dtype=time.dtype)[:, None, :]
            if self.fused:
                linear = m.action_time_mlp_in
                steps.append(TimeEmbedding(None, torch.nn.functional.linear(emb.reshape(-1), linear.weight[:, width:], linear.bias)))
            else:
                steps.append(TimeEmbedding(emb, None))
        self.conditioning = tuple(steps)  # type: ignore[assignment]
        return self.conditioning  # type: ignore[return-value]

    def _sample_constants(self, inputs: SamplerInputs) -> Tensor:
        """The state token's embedding ``(B, 1, W)``: the same at every step."""
        if inputs.state is None:
            raise ValueError("π0's static sampler needs the state (SamplerInputs.state)")
        proj = self.model.state_proj
        state = inputs.state.to(torch.float32) if proj.weight.dtype == torch.float32 else inputs.state
        return proj(state)[:, None, :]

    def _embed_suffix(self, x_t: Tensor, cond: TimeEmbedding, fixed: Tensor) -> Tensor:  # type: ignore[override]
        """LeRobot's ``embed_suffix``: the state token, then the actions with the time mixed in."""
        m = self.model
        actions = m.action_in_proj(x_t)
        if cond.bias is not None:  # folded: W_a · a + (W_t · t + b)
            width = actions.shape[-1]
            mixed = torch.nn.functional.linear(actions, m.action_time_mlp_in.weight[:, :width], cond.bias)
        else:
            assert cond.embedding is not None
            mixed = m.action_time_mlp_in(torch.cat([actions, cond.embedding.expand_as(actions)], dim=2))
        actions = m.action_time_mlp_out(torch.nn.functional.silu(mixed))
        return self.ops.stream(torch.cat([fixed.to(actions.dtype), actions], dim=1), self._dtype(self.expert))

    @staticmethod
    def _layer_conditioning(cond: Any, layer: int) -> tuple[()]:
        return ()

    def _expert_layer(self, layer: Any, h: Tensor, x: Tensor, cache: Any, mask: Tensor, rope: tuple[Tensor, Tensor]) -> tuple[Tensor, Pending]:  # type: ignore[override]
        """One action-expert layer (plain norms, no gates), its input ``x`` normed already: the
        suffix's keys and values written into ``cache`` behind the prefix's; returns the residual
        stream and the MLP's sum left pending."""
        return self._plain_layer(layer, h, x, cache, self.ops.length(cache) - h.shape[1], cache, mask, rope)

    def _final_norm(self, h: Tensor, cond: Any) -> Tensor:
        return self.ops.final_norm(self.expert.norm, h)
