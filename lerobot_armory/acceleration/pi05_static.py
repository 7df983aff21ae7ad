"""A static sampler for LeRobot's π0.5: the same computation as ``PI05Pytorch.sample_actions``,
written so that one batch shape is one fixed sequence of kernels (what a CUDA graph records).

Why: LeRobot 0.6.1's sampler is launch-bound on a GPU (≈ 250 ms a batch on an H100 where the
arithmetic is a few tens of ms). It cannot be captured as it is, because every sample
- builds attention masks and timesteps from Python lists (``torch.tensor(list, device=...)``: a
  blocking host-to-device copy, forbidden while a graph is recorded);
- clones the prefix KV cache at every denoising step (``clone_past_key_values``: 18 layers' K and
  V copied 10 times), and HF's ``DynamicCache.update`` then concatenates the suffix onto it.

:class:`StaticPi05` runs the policy's own modules (LeRobot's and HF's: the SigLIP tower, the
embedding, every projection, norm, MLP and rotary table; no weight is copied and nothing of
LeRobot is forked) in the order ``sample_actions`` runs them, with these changes:
- the prefix writes its keys and values once into one buffer per layer that has room for the
  suffix; each denoising step writes the suffix's keys and values in place behind them (no clone,
  no concatenation);
- all cameras pass the vision tower as one batch (LeRobot runs it once per camera);
- masks and positions are computed on the device from the inputs' pad masks; the flow times and
  RTC guidance weights are device tensors made once, indexed by step;
- everything that depends on the flow time alone — the time embedding, the time MLP and every
  adaptive norm's scale, shift and gate (two per expert layer and the final norm) — is computed
  once by the same modules (:meth:`StaticPi05.prepare`), not at every step of every sample: every
  row of a batch shares the flow time, so one row of each broadcasts over any batch, and no shape
  depends on the batch size but the inputs' (one compilation serves every batch size);
- RTC's guidance is closed-form (see below), with one weight row and one leftover per batch row
  as inputs, so a guided batch is the same graph as an unguided one;
- each layer's operations come from ``pi05_kernels``: ``Fused`` by default (the same values with
  less than half the kernels: fused projections, one-kernel norms with the time conditioning
  folded into their weight and the next projection's bias, q, k and v rotated together and
  stored straight into the cache, a float32 residual stream), or ``LeRobotOrder``
  (``fused=False``), LeRobot's and HF's operations one for one.

Row independence: no operation mixes batch rows, so a batch padded with extra rows gives its
real rows exactly what the same rows give in a batch of the padded size. The engine pads a
batch to a bucket size (``engine/cuda_graphs.py``).

RTC: LeRobot 0.6.1 evaluates the velocity before marking ``x_t`` as requiring a gradient, so its
"vector-Jacobian product" is taken through ``x_t - t·v`` with ``v`` held fixed: the correction is
the weighted error itself, ``(leftover - (x_t - t·v)) · w``. The step here computes that directly
(``tests/policies/test_pi05_static.py`` checks it against LeRobot's processor); ``engine/rtc.py`` supplies
the per-row weights from LeRobot's own ``get_prefix_weights``.

Numerics: with ``fused=False`` and ``attention="eager"`` every operation is the one LeRobot runs, in its dtype
(``--policy.dtype=bfloat16`` keeps LeRobot's float32 islands: the vision tower, the projector,
the norms, the time MLP, the action projections). The K/V layout for grouped-query attention
(one K/V head for eight query heads) is broadcast instead of copied, which may change float
rounding in the last bit. ``attention="sdpa"`` uses ``F.scaled_dot_product_attention`` with
LeRobot's additive mask (same masking, a fused kernel on a GPU). The fused kernels compute the
same values in another rounding order (``pi05_kernels``: 4.8e-7 from LeRobot's chunks in float32)
and, in bfloat16, keep the residual stream in float32: their chunks are about as near a float32
model's as LeRobot's bf16 chunks, nearer on π0.5 (``benchmarks/bf16_accuracy.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from lerobot.policies.common.vla_utils import create_sinusoidal_pos_embedding
from lerobot.utils.constants import OPENPI_ATTENTION_MASK_VALUE
from torch import Tensor

from lerobot_armory.policies.cameras import served_cameras
from lerobot_armory.acceleration.pi05_kernels import KEY_ALIGN, Fused, LeRobotOrder, Modulation, Pending
from lerobot_armory.acceleration.rtc_guidance import guidance_weight

ATTENTION = ("eager", "sdpa")


@dataclass(frozen=True)
class StepConditioning:
    """The expert's time conditioning at one flow step: per layer (input norm, post-attention norm),
    and the final norm."""

    layers: tuple[tuple[Modulation, Modulation], ...]
    final: Modulation


@dataclass
class SamplerInputs:
    """One batch, as the sampler takes it (every tensor on the model's device, batch rows first).

    Attributes:
        images: one ``(B, 3, H, W)`` float tensor per camera of the policy a robot sends
            (:func:`served_cameras`), as LeRobot's pre-processor hands them to
            ``predict_action_chunk`` (in [0, 1]).
        tokens / masks: the prompt's token ids ``(B, L)`` and attention mask ``(B, L)``.
        noise: ``(B, chunk_size, max_action_dim)`` float32, the flow's starting point.
        rtc_weights: ``(B, chunk_size, 1)`` float32 guidance weights (zeros: no guidance), or
            None when the sampler was built without RTC.
        rtc_leftover: ``(B, chunk_size, max_action_dim)`` float32 actions to guide toward.
        state: ``(B, max_state_dim)`` the state, padded as the policy pads it, for a sampler that
            embeds it (π0: :attr:`StaticPi05.takes_state`); None for π0.5, whose prompt holds it.
    """

    images: tuple[Tensor, ...]
    tokens: Tensor
    masks: Tensor
    noise: Tensor
    rtc_weights: Tensor | None = None
    rtc_leftover: Tensor | None = None
    state: Tensor | None = None

    @property
    def rows(self) -> int:
        return int(self.noise.shape[0])

    def tensors(self) -> list[Tensor]:
        """Every tensor, in a fixed order (a CUDA graph's static inputs)."""
        out = [*self.images, self.tokens, self.masks, self.noise]
        if self.state is not None:
            out.append(self.state)
        if self.rtc_weights is not None:
            assert self.rtc_leftover is not None
            out += [self.rtc_weights, self.rtc_leftover]
        return out

    def with_tensors(self, tensors: Sequence[Tensor]) -> SamplerInputs:
        """The same structure over other tensors (in :meth:`tensors` order)."""
        n = len(self.images)
        state = tensors[n + 3] if self.state is not None else None
        rtc = tuple(tensors[n + 3 + (state is not None) :])
        return SamplerInputs(tuple(tensors[:n]), tensors[n], tensors[n + 1], tensors[n + 2], *(rtc or (None, None)), state=state)

    @property
    def prompt_length(self) -> int:
        """Token columns of the prompt (π0 and π0.5 pad every prompt to their tokenizer's max
        length; SmolVLA pads a batch's prompts to its longest)."""
        return int(self.tokens.shape[1])

    def prompt_fitted(self, length: int) -> SamplerInputs:
        """The same batch with exactly ``length`` prompt columns: the first ``length`` of them, or
        all of them followed by masked padding (token 0, mask false). The caller makes sure every
        dropped column is padding in every row: padding is masked everywhere (as a key; a padded
        query row is never read), so the chunks are the same up to the rounding of sums of another
        length. Why padding: a CUDA graph holds one prompt length, and SmolVLA's tokenizer pads a
        batch to its longest prompt, a different length nearly every batch.

        The columns are copied into tensors of the standard strides, not viewed: a compiled
        sampler's guards check strides, and a padded or recorded batch has them, so a view would
        be one more compilation (a few hundred integers a row). ``contiguous()`` is not enough:
        one row of a view is contiguous already, with the full prompt's row stride."""
        if length < 1:
            raise ValueError(f"a prompt needs at least one column, got {length}")
        if length <= self.prompt_length:
            tokens, masks = (t[:, :length].clone(memory_format=torch.contiguous_format) for t in (self.tokens, self.masks))
        else:
            extra = length - self.prompt_length
            tokens = torch.cat([self.tokens, self.tokens.new_zeros(self.rows, extra)], dim=1)
            masks = torch.cat([self.masks, self.masks.new_zeros(self.rows, extra)], dim=1)
        return SamplerInputs(self.images, tokens, masks, self.noise, self.rtc_weights, self.rtc_leftover, self.state)

    def padded(self, rows: int) -> SamplerInputs:
        """The same batch grown to ``rows`` by repeating its last row (padding must be valid data:
        rows never mix, but a row of garbage could hold NaN/inf and a profiler would see it)."""
        extra = rows - self.rows
        if extra < 0:
            raise ValueError(f"cannot pad a batch of {self.rows} to {rows}")
        if extra == 0:
            return self

        def grow(t: Tensor | None) -> Tensor | None:
            return None if t is None else torch.cat([t, t[-1:].expand(extra, *t.shape[1:])])

        return SamplerInputs(
            tuple(grow(i) for i in self.images),  # type: ignore[misc]
            grow(self.tokens), grow(self.masks), grow(self.noise),  # type: ignore[arg-type]
            grow(self.rtc_weights), grow(self.rtc_leftover), grow(self.state),
        )  # fmt: skip


def policy_type(policy: Any) -> str:
    """LeRobot's ``config.type`` of ``policy`` (its class name when it has none)."""
    return getattr(getattr(policy, "config", None), "type", type(policy).__name__)


@dataclass(frozen=True)
class FlowSchedule:
    """LeRobot's Euler schedule (``euler_integrate``): ``t = 1 + k·dt``, ``dt = -1/steps``; the flow
    times as a device table, and RTC's guidance weight per step (None: unguided)."""

    dt: float
    times: list[float]
    time_table: Tensor
    guidance_table: Tensor | None

    @classmethod
    def make(cls, steps: int, guided: bool, max_guidance_weight: float, device: torch.device) -> FlowSchedule:
        dt = -1.0 / steps
        times = [1.0 + k * dt for k in range(steps)]
        guidance = torch.stack([guidance_weight(t, max_guidance_weight) for t in times]).to(device) if guided else None
        return cls(dt, times, torch.tensor(times, dtype=torch.float32, device=device), guidance)


def _text_model(pwe: Any) -> Any:
    return pwe.paligemma.model.language_model


def vision_dtype_of(policy: Any) -> torch.dtype | None:
    """The dtype a π0 / π0.5 SigLIP tower holds its weights in (None: no PaliGemma tower)."""
    tower = getattr(getattr(getattr(getattr(policy, "model", None), "paligemma_with_expert", None), "paligemma", None), "model", None)
    params = getattr(getattr(tower, "vision_tower", None), "parameters", None)
    first = next(params(), None) if params is not None else None
    return None if first is None else first.dtype


class StaticPi05:
    """``PI05Pytorch.sample_actions`` without host synchronisation or per-step copies.

    The base of the π0 family's static samplers: a subclass (``pi0_static.StaticPi0``) changes
    what is specific to its model, the time conditioning (:meth:`prepare`), the suffix's tokens
    (:meth:`_embed_suffix`, :attr:`suffix_pattern`), an expert layer and the final norm; the
    prefix, the caches, the Euler loop and RTC are shared.

    Args:
        policy: a loaded LeRobot ``PI05Policy`` (its weights are used in place).
        guided: take RTC inputs (``SamplerInputs.rtc_*``) and apply LeRobot's guidance.
        max_guidance_weight: RTC's clamp (LeRobot's ``RTCConfig.max_guidance_weight``).
        attention: ``eager`` (LeRobot's own attention math) or ``sdpa``.
        fused: run each layer with fewer kernels (``pi05_kernels.Fused``: the same values in
            another rounding order; the layers' q/k/v and gate/up weights become views of one
            tensor each) where the policy allows it (:attr:`unfused_reason` says why not);
            False: LeRobot's own sequence of operations.
        vision_dtype: cast the SigLIP tower and the projector to this dtype (in place, once: the
            float32 weights are gone) and so run them in it — LeRobot's ``embed_image`` hands the
            tower float32 images, which SigLIP casts to its patch weights' dtype; None: as loaded
            (LeRobot keeps them in float32).

    Raises:
        ValueError: the policy is not supported (:meth:`unsupported_reason`) or a bad option.
    """

    kind = "pi05"  # LeRobot's ``config.type``
    model_name = "PI05Pytorch"
    model_parts: tuple[str, ...] = ("action_in_proj", "action_out_proj", "time_mlp_in", "time_mlp_out")
    adaptive_norms = True  # the expert's norms take the flow time (π0.5's adaRMS)
    # The VLM's MLPs (the prefix's rows: 256 a camera and the prompt's, a sample) run gate and up as two contiguous
    # products (``Fused.mlp``'s ``apart``); the expert's 50 rows a sample keep one product.
    vlm_mlp_apart = True
    takes_state = False  # the sampler embeds the state (SamplerInputs.state); π0.5's prompt holds it
    state_tokens = 0  # suffix tokens before the actions
    compilable = True  # --engine.compile_sampler: compile_layers()

    def __init__(
        self,
        policy: Any,
        guided: bool = False,
        max_guidance_weight: float = 10.0,
        attention: str = "eager",
        fused: bool = True,
        vision_dtype: torch.dtype | None = None,
    ) -> None:
        why = self.unsupported_reason(policy)
        if why is not None:
            raise ValueError(why)
        if attention not in ATTENTION:
            raise ValueError(f"attention must be one of {', '.join(ATTENTION)}, got {attention!r}")
        self.policy = policy
        self.model = policy.model
        self.config = policy.config
        self.guided = guided
        self.attention = attention
        self.mask_value = float(OPENPI_ATTENTION_MASK_VALUE)
        pwe = self.model.paligemma_with_expert
        self.vlm = _text_model(pwe)
        self.expert = pwe.gemma_expert.model
        self.unfused_reason: str | None = None
        self.ops: LeRobotOrder = LeRobotOrder(attention)
        if fused:
            try:  # Fused checks every layer before it touches a weight
                self.ops = Fused([self.vlm, self.expert], attention)
            except ValueError as exc:
                self.unfused_reason = str(exc)
        self.fused = isinstance(self.ops, Fused)
        self.mlp_apart = self.vlm_mlp_apart  # this sampler's, read once (gpu_profile's A/B patches the class's)
        self.cameras = served_cameras(self.config)  # read once: a traced region cannot read config.type
        self.chunk_size = int(self.config.chunk_size)
        self.suffix_length = self.state_tokens + self.chunk_size
        self.num_steps = int(self.config.num_inference_steps)
        if self.num_steps < 1:
            raise ValueError(f"num_inference_steps must be >= 1, got {self.num_steps}")
        if vision_dtype is not None:  # after every check: a refused sampler leaves the weights as they were
            paligemma = pwe.paligemma.model
            _cast_all_or_nothing([paligemma.vision_tower, paligemma.multi_modal_projector], vision_dtype)
        device = next(self.model.parameters()).device
        # Which suffix token attends which (LeRobot's ``make_att_2d_masks`` of its suffix's
        # attention pattern): π0.5's actions attend each other fully; made here, once.
        self.suffix_pattern = self._suffix_pattern().to(device)
        self.no_keys = torch.zeros(1, self.suffix_length, KEY_ALIGN, dtype=torch.bool, device=device)  # the caches' gap, masked
        # LeRobot's Euler schedule: t = 1 + k·dt, dt = -1/steps, each t a float32 tensor.
        schedule = FlowSchedule.make(self.num_steps, guided, max_guidance_weight, device)
        self.dt, self.times, self.time_table, self.guidance_table = schedule.dt, schedule.times, schedule.time_table, schedule.guidance_table
        self.conditioning: tuple[StepConditioning, ...] | None = None  # made once (prepare)
        self._compiled: tuple[Any, Any] | None = None  # compile_layers()

    @classmethod
    def unsupported_reason(cls, policy: Any) -> str | None:
        """Why this sampler cannot run ``policy`` (None: it can)."""
        config, model, kind = getattr(policy, "config", None), getattr(policy, "model", None), policy_type(policy)
        if kind != cls.kind:
            return f"{kind} is not {cls.kind}"
        pwe = getattr(model, "paligemma_with_expert", None)
        if pwe is None or any(not hasattr(model, part) for part in cls.model_parts):
            return f"{type(model).__name__} is not LeRobot 0.6's {cls.model_name}"
        if getattr(config, "gradient_checkpointing", False):
            return "gradient checkpointing is a training option"
        vlm, expert = _text_model(pwe), pwe.gemma_expert.model
        if len(vlm.layers) != len(expert.layers):
            return f"the VLM has {len(vlm.layers)} layers and the expert {len(expert.layers)}: {cls.kind} pairs them one to one"
        for name, layers in (("VLM", vlm.layers), ("expert", expert.layers)):
            attn = layers[0].self_attn
            if attn.q_proj.out_features != attn.config.num_attention_heads * attn.head_dim:
                return f"the {name}'s attention projections do not match its head count"
        heads = {(lay.self_attn.config.num_key_value_heads, lay.self_attn.head_dim) for lay in (*vlm.layers, *expert.layers)}
        if len(heads) != 1:
            return f"the VLM's and the expert's K/V heads differ ({sorted(heads)}): they cannot share a cache"
        norms = [expert.norm, *(n for lay in expert.layers for n in (lay.input_layernorm, lay.post_attention_layernorm))]
        if any((getattr(n, "dense", None) is not None) != cls.adaptive_norms for n in norms):
            want = "all take" if cls.adaptive_norms else "take none of"
            return f"the action expert's norms do not match {cls.kind}'s, which {want} the flow time"
        return None

    def _suffix_pattern(self) -> Tensor:
        """``(S, S)`` bool: suffix token i attends suffix token j (and every valid prefix token).
        LeRobot's pattern for π0 and π0.5 (``make_att_2d_masks`` of its ``att_masks``): the state
        tokens (π0's one; π0.5 has none) attend each other, not the actions; every action attends
        the whole suffix."""
        pattern = torch.ones(self.suffix_length, self.suffix_length, dtype=torch.bool)
        pattern[: self.state_tokens, self.state_tokens :] = False
        return pattern

    # -- the sampler ---------------------------------------------------------------------------

    @torch.no_grad()
    def prepare(self) -> tuple[StepConditioning, ...]:
        """The time conditioning of every flow step, computed once by LeRobot's modules for one
        row (every row of a batch has the same flow time: LeRobot computes the same row B times)
        and kept: call it outside a traced or recorded region (``sample`` calls it if needed)."""
        if self.conditioning is not None:
            return self.conditioning
        dtype = self._dtype(self.expert)
        steps = []
        for step in range(self.num_steps):
            cond = self._time_condition(self.time_table[step].expand(1))
            layers = tuple(
                (
                    self.ops.fold(self._modulation(lay.input_layernorm, cond, dtype), lay.self_attn),
                    self.ops.fold(self._modulation(lay.post_attention_layernorm, cond, dtype), lay.mlp),
                )
                for lay in self.expert.layers
            )
            steps.append(StepConditioning(layers, self._modulation(self.expert.norm, cond, dtype)))
        self.conditioning = tuple(steps)
        return self.conditioning

    def _time_condition(self, time: Tensor) -> Tensor:
        """LeRobot's ``embed_suffix`` time path: sinusoidal embedding, then the time MLP."""
        m = self.model
        time_emb = create_sinusoidal_pos_embedding(
            time, m.action_in_proj.out_features, min_period=self.config.min_period, max_period=self.config.max_period, device=time.device
        ).type(dtype=time.dtype)
        return torch.nn.functional.silu(m.time_mlp_out(torch.nn.functional.silu(m.time_mlp_in(time_emb))))

    @staticmethod
    def _modulation(norm: Any, cond: Tensor, dtype: torch.dtype) -> Modulation:
        """``PiGemmaRMSNorm.forward``'s conditioning half, for inputs of ``dtype`` (B, L, W)."""
        scale, shift, gate = norm.dense(cond).unsqueeze(1).chunk(3, dim=-1)
        return Modulation(1 + scale.float(), shift.float(), gate.to(dtype))

    def compile_layers(self) -> None:
        """``torch.compile`` (inductor, each a whole graph) the two layer functions every sample
        runs 18 and 180 times, a VLM layer over the prefix and an action-expert layer, for
        :meth:`sample_compiled`. Compiled per layer, not per sample: one compilation serves every
        layer of a kind (they differ in weights only, which torch.compile takes as inputs), so a
        compilation traces one layer, not the model's full depth (narrow π0.5, 2-core CPU: one
        compilation of the whole sampler took 608 s, all four of these 30 s). The inputs' batch
        and prompt dimensions are marked dynamic: a function compiles once for one row and once
        for every larger batch at every prompt length. The vision tower and each step's action
        projections stay eager."""
        if self._compiled is not None:
            return
        vlm, expert = torch.compile(self._vlm_layer, fullgraph=True), torch.compile(self._expert_layer, fullgraph=True)

        def vlm_layer(layer: Any, h: Tensor, x: Tensor, cache: Any, mask: Tensor, rope: tuple[Tensor, Tensor]) -> tuple[Tensor, Pending]:
            _mark_dynamic((h, x, cache, mask, rope), h.shape[0], {x.shape[1], self.ops.length(cache)})
            return vlm(layer, h, x, cache, mask, rope)

        def expert_layer(layer: Any, h: Tensor, x: Tensor, cache: Any, mask: Tensor, rope: tuple[Tensor, Tensor], *mods: Modulation) -> tuple[Tensor, Pending]:
            # The suffix's length is fixed (the chunk, and π0's state token): only the cache's varies.
            _mark_dynamic((h, x, cache, mask, rope), h.shape[0], {self.ops.length(cache)})
            return expert(layer, h, x, cache, mask, rope, *mods)

        self._compiled = (vlm_layer, expert_layer)

    def sample_compiled(self, inputs: SamplerInputs) -> Tensor:
        """:meth:`sample` through the compiled layers (:meth:`compile_layers` first)."""
        return self.sample_embedded_compiled(inputs, self.vision(inputs.images))

    def sample_embedded_compiled(self, inputs: SamplerInputs, vision: tuple[Tensor, ...]) -> Tensor:
        """:meth:`sample_embedded` through the compiled layers (:meth:`compile_layers` first)."""
        if self._compiled is None:
            raise RuntimeError("compile_layers() first")
        return self.sample_embedded(inputs, vision, layers=self._compiled)

    @torch.no_grad()
    def sample(self, inputs: SamplerInputs, layers: tuple[Any, Any] | None = None) -> Tensor:
        """Actions ``(B, chunk_size, max_action_dim)`` float32 for one batch (LeRobot's
        ``sample_actions`` given the same noise; the RTC guidance per row when ``guided``).
        ``layers``: the VLM and expert layer functions (default: :meth:`_vlm_layer`,
        :meth:`_expert_layer`)."""
        return self.sample_embedded(inputs, self.vision(inputs.images), layers)

    @torch.no_grad()
    def vision(self, images: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
        """What of the prefix depends on the images alone: each camera's embeddings (LeRobot's
        ``_preprocess_images`` and ``embed_image``, its missing cameras included), then each
        camera's mask. A CUDA graph of its own, so that the engine can start it before the
        batch's prompt is tokenized (``BucketedSampler.start``)."""
        images, img_masks = self.policy._preprocess_images(dict(zip(self.cameras, images, strict=True)))
        return (*self._embed_images(images), *img_masks)

    @torch.no_grad()
    def sample_embedded(self, inputs: SamplerInputs, vision: tuple[Tensor, ...], layers: tuple[Any, Any] | None = None) -> Tensor:
        """:meth:`sample` given :meth:`vision`'s output for ``inputs.images`` (not read here)."""
        vlm_layer, expert_layer = layers or (self._vlm_layer, self._expert_layer)
        if self.guided != (inputs.rtc_weights is not None):
            raise ValueError("RTC inputs must be given exactly when the sampler is guided")
        cameras = len(vision) // 2
        prefix_embs, prefix_pad = self._embed_prefix(vision[:cameras], vision[cameras:], inputs.tokens, inputs.masks)
        caches = self._prefix_cache(prefix_embs, prefix_pad, vlm_layer)
        # What every denoising step shares: the suffix attends every valid prefix token and the
        # suffix as its pattern says; its positions follow the prefix's valid tokens.
        b, p, s = prefix_pad.shape[0], prefix_pad.shape[1], self.suffix_length
        gap = self.ops.cache_length(p, s) - p - s  # positions the ops' caches add between prefix and suffix (masked)
        parts = [prefix_pad[:, None, :].expand(b, s, p), self.suffix_pattern.expand(b, s, s)]
        if gap:
            parts.insert(1, self.no_keys[:, :, :gap].expand(b, s, gap))  # a view: no kernel
        valid = torch.cat(parts, dim=2)
        mask = self.ops.mask(self._additive(valid), self._dtype(self.expert))
        positions = prefix_pad.sum(dim=-1)[:, None] + torch.arange(s, device=prefix_pad.device)[None, :]
        rope = self.ops.rope(self.expert, self._like(self.expert, inputs.noise), positions)
        conditioning = self.prepare()
        fixed = self._sample_constants(inputs)
        x_t = inputs.noise
        for step, time in enumerate(self.times):
            v_t = self._velocity(x_t, conditioning[step], fixed, caches, mask, rope, expert_layer)
            if self.guided:
                assert self.guidance_table is not None and inputs.rtc_leftover is not None
                # LeRobot's correction, closed form (module docstring): the weighted error.
                err = (inputs.rtc_leftover - (x_t - time * v_t)) * inputs.rtc_weights
                v_t = v_t - self.guidance_table[step] * err
            x_t = self.ops.euler(x_t, v_t, self.dt)
        return x_t

    def _embed_images(self, images: Sequence[Tensor]) -> tuple[Tensor, ...]:
        """Each camera's image embeddings. All cameras go through the vision tower as one batch
        (LeRobot runs it once per camera): rows never mix, and one pass of 2B images launches half
        the kernels of two passes of B."""
        pwe = self.model.paligemma_with_expert
        # Shapes compared pairwise, not hashed into a set: a compiler with a dynamic batch size
        # would have to make the batch size a constant to hash it (one compilation per size).
        if len(images) > 1 and all(i.shape == images[0].shape for i in images[1:]):
            return tuple(pwe.embed_image(torch.cat(list(images))).split(images[0].shape[0]))
        return tuple(pwe.embed_image(img) for img in images)

    def _embed_prefix(self, per_camera: Sequence[Tensor], img_masks: Sequence[Tensor], tokens: Tensor, masks: Tensor) -> tuple[Tensor, Tensor]:
        """LeRobot's ``embed_prefix`` from the images' embeddings, without its host-built
        attention pattern (all zeros for π0.5: the prefix attends itself fully, so only the pad
        mask matters)."""
        pwe = self.model.paligemma_with_expert
        embs, pads = [], []
        for emb, img_mask in zip(per_camera, img_masks, strict=True):
            embs.append(emb)
            pads.append(img_mask[:, None].expand(emb.shape[0], emb.shape[1]))
        embs.append(pwe.embed_language_tokens(tokens))
        pads.append(masks)
        return torch.cat(embs, dim=1), torch.cat(pads, dim=1)

    def _prefix_cache(self, embs: Tensor, pad: Tensor, vlm_layer: Any) -> list[Any]:
        """Run the VLM over the prefix; return per layer a K/V cache (the ops' layout) of
        ``P + S`` positions (S: the suffix's; the ops may round that up, the positions between zero)
        with the prefix's (post-rotary) keys and values in the first ``P``."""
        p = pad.shape[1]
        mask = self.ops.mask(self._additive(pad[:, None, :] & pad[:, :, None]), self._dtype(self.vlm))
        positions = torch.cumsum(pad, dim=1) - 1
        h = self.ops.stream(embs, self._dtype(self.vlm))
        rope = self.ops.rope(self.vlm, self._like(self.vlm, embs), positions)
        caches = []
        last = len(self.vlm.layers) - 1
        pending: Pending = None
        for i, layer in enumerate(self.vlm.layers):
            h, x = self.ops.enter(h, pending, layer.input_layernorm, None)
            cache = self.ops.new_cache(layer.self_attn, x, p, self.suffix_length)
            caches.append(cache)
            if i == last:  # the last layer's output is never read: only its keys and values are
                self.ops.qkv(layer.self_attn, x, rope, cache, 0)
                break
            h, pending = vlm_layer(layer, h, x, cache, mask, rope)
        return caches

    def _vlm_layer(self, layer: Any, h: Tensor, x: Tensor, cache: Any, mask: Tensor, rope: tuple[Tensor, Tensor]) -> tuple[Tensor, Pending]:
        """One VLM layer over the prefix, its input ``x`` normed already: keys and values into
        ``cache`` (from position 0); returns the residual stream and the MLP's sum left pending."""
        return self._plain_layer(layer, h, x, cache, 0, self.ops.cached(cache, x.shape[1]), mask, rope, self.mlp_apart)

    def _plain_layer(
        self, layer: Any, h: Tensor, x: Tensor, cache: Any, start: int, kv: Any, mask: Tensor, rope: tuple[Tensor, Tensor], mlp_apart: bool = False
    ) -> tuple[Tensor, Pending]:
        """A Gemma layer with plain norms, its input ``x`` normed already: keys and values into
        ``cache`` from ``start``, attention over ``kv`` (the cache's attended part); ``mlp_apart``:
        the MLP's gate and up as two products (the ops' ``mlp``). Returns the residual stream and
        the MLP's output, whose residual sum the next layer adds with its input norm (``enter``)."""
        q = self.ops.qkv(layer.self_attn, x, rope, cache, start)
        y = self.ops.project_out(layer.self_attn.o_proj, self.ops.attend(layer.self_attn, q, kv, mask))
        h, x = self.ops.residual_norm(h, y, None, layer.post_attention_layernorm, None)
        return h, (self.ops.mlp(layer.mlp, x, None, mlp_apart), None)

    def _velocity(
        self, x_t: Tensor, cond: Any, fixed: Any, caches: list[Any], mask: Tensor, rope: tuple[Tensor, Tensor], expert_layer: Any
    ) -> Tensor:
        """One denoising step of the action expert (LeRobot's ``denoise_step``): ``cond`` is the
        step's time conditioning (:meth:`prepare`), ``fixed`` what a sample's steps share
        (:meth:`_sample_constants`)."""
        h, pending = self._embed_suffix(x_t, cond, fixed), None
        for i, layer in enumerate(self.expert.layers):
            # The input norm here, outside a compiled layer (as the VLM's): a first layer with no
            # sum pending would be a second compilation of it; between compiled layers it is one
            # Triton kernel with the sum (Fused.triton_here).
            mods = self._layer_conditioning(cond, i)
            h, x = self.ops.enter(h, pending, layer.input_layernorm, mods[0] if mods else None)
            h, pending = expert_layer(layer, h, x, caches[i], mask, rope, *mods)
        assert pending is not None  # a model without layers fails before (the layers[0] it reads at construction)
        h = self.ops.residual(h, *pending)
        # The norm is per token: the actions' rows alone give the same values.
        return self.model.action_out_proj(self._final_norm(h[:, -self.chunk_size :], cond).to(dtype=torch.float32))

    # -- what π0.5's model does its own way (a subclass changes these) ---------------------------

    def _sample_constants(self, inputs: SamplerInputs) -> Any:
        """What every denoising step of a sample reads besides ``x_t`` (π0.5: nothing)."""
        return None

    def _embed_suffix(self, x_t: Tensor, cond: StepConditioning, fixed: Any) -> Tensor:
        """The suffix's tokens, as the expert's residual stream (π0.5: the actions, projected)."""
        return self.ops.stream(self.model.action_in_proj(x_t), self._dtype(self.expert))

    @staticmethod
    def _layer_conditioning(cond: StepConditioning, layer: int) -> tuple[Modulation, ...]:
        """What ``_expert_layer`` takes after its common arguments, for layer ``layer``."""
        return cond.layers[layer]

    def _final_norm(self, h: Tensor, cond: StepConditioning) -> Tensor:
        return self.ops.ada_norm(self.expert.norm, h, cond.final)

    def _expert_layer(
        self, layer: Any, h: Tensor, x: Tensor, cache: Any, mask: Tensor, rope: tuple[Tensor, Tensor], mod_in: Modulation, mod_post: Modulation
    ) -> tuple[Tensor, Pending]:
        """One action-expert layer, its input ``x`` normed already (with ``mod_in``): the suffix's
        keys and values written into ``cache`` in place, behind the prefix's (its last
        ``chunk_size`` positions); returns the residual stream and the MLP's sum left pending."""
        q = self.ops.qkv(layer.self_attn, x, rope, cache, self.ops.length(cache) - h.shape[1], mod_in.bias)
        y = self.ops.project_out(layer.self_attn.o_proj, self.ops.attend(layer.self_attn, q, cache, mask))
        h, x = self.ops.residual_norm(h, y, mod_in.gate, layer.post_attention_layernorm, mod_post)
        return h, (self.ops.mlp(layer.mlp, x, mod_post.bias), mod_post.gate)

    def _additive(self, valid: Tensor) -> Tensor:
        """LeRobot's additive mask (B, Lq, Lk): 0 where attended, its large negative constant elsewhere."""
        return torch.where(valid, 0.0, self.mask_value)

    @classmethod
    def _like(cls, text_model: Any, x: Tensor) -> Tensor:
        """An empty tensor of ``text_model``'s dtype on ``x``'s device: what a rotary table reads
        of its input (HF's ``rotary_emb`` takes only its dtype and device)."""
        return torch.empty(0, dtype=cls._dtype(text_model), device=x.device)

    @classmethod
    def _dtype(cls, text_model: Any) -> torch.dtype:
        """The dtype of ``text_model``'s hidden states (and attention scores)."""
        return torch.bfloat16 if cls._bf16(text_model) else torch.float32

    @staticmethod
    def _bf16(text_model: Any) -> bool:
        # PiGemmaModel.forward casts its input to bfloat16 when its layers are bfloat16.
        return len(text_model.layers) > 0 and text_model.layers[0].self_attn.q_proj.weight.dtype == torch.bfloat16


def _cast_all_or_nothing(modules: Sequence[Any], dtype: torch.dtype) -> None:
    """``module.to(dtype)`` for ``modules``' floating-point parameters and buffers, all or nothing:
    every cast tensor is made before any replaces its original, so a failure on the way (out of
    memory: the cast copies coexist with the originals until the swap) leaves every module as it
    was, where ``Module.to`` would leave the first ones cast and the rest not."""
    originals = [t for m in modules for t in (*m.parameters(), *m.buffers()) if t.is_floating_point() and t.dtype != dtype]
    cast = [t.detach().to(dtype) for t in originals]
    with torch.no_grad():
        for t, c in zip(originals, cast, strict=True):
            t.data = c


def _mark_dynamic(tensors: Sequence[Any], batch: int, lengths: set[int]) -> None:
    """Mark the batch and prompt dimensions of ``tensors`` (nested in tuples too) dynamic for
    torch.compile: dimension 0 of size ``batch``, and every later one whose size is in
    ``lengths`` (``maybe``: a dimension the code specialises costs a compilation, not an error; a
    static one marked by a coincidence of sizes only loses its specialisation)."""
    for t in tensors:
        if isinstance(t, tuple):
            _mark_dynamic(t, batch, lengths)
            continue
        if t.shape[0] == batch:
            torch._dynamo.maybe_mark_dynamic(t, 0)
        for dim in range(1, t.dim()):
            if t.shape[dim] in lengths:
                torch._dynamo.maybe_mark_dynamic(t, dim)
