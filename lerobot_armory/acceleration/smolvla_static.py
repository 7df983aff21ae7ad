"""A static sampler for LeRobot's SmolVLA: ``VLAFlowMatching.sample_actions`` as one fixed sequence
of kernels per batch shape (what a CUDA graph records), in LeRobot's own order of operations.

Why: LeRobot 0.6.1's SmolVLA cannot be recorded as it is. Every sample builds its attention
patterns and flow times from Python lists (``torch.tensor(list, device=...)``: a host-to-device
copy, forbidden while a graph records), scales the image embeddings by a ``torch.tensor`` of a
Python float, and HF's SmolVLM vision embeddings write their position ids through a boolean mask
(``position_ids[mask] = ...``: an output whose size depends on the data, so the host waits). It
also recomputes, at every denoising step, what depends on the prefix alone.

:class:`StaticSmolVLA` runs the policy's own modules (the vision tower, the connector, every
projection, norm and MLP, LeRobot's ``apply_rope`` and ``eager_attention_forward``; nothing copied
or forked) in the order ``sample_actions`` runs them, with these changes:

- the vision embeddings' position ids are computed from the image's shape by HF's formula for a
  full patch mask (no boolean indexing), and the encoder gets no mask (all patches attend all:
  HF's full-mask case);
- the prefix's attention pattern (images and language attend each other, the state token
  attends everything before it) and the suffix's (causal) are built on the device; the image
  scale and the special image tokens' embeddings are made once (:meth:`prepare`);
- the prefix writes its keys and values once per self-attention layer into a buffer with room for
  the suffix, and each step writes the suffix's in place behind them (LeRobot appends to HF's
  cache, then crops it); a cross-attention layer's keys and values — the expert's projections of
  the VLM's prefix keys and values — are computed once a sample, not at every step;
- RTC's guidance is closed-form, as in :mod:`.pi05_static` (one weight row and leftover per batch
  row, so guided and unguided batches share one graph).

Row independence holds (no operation mixes batch rows), so bucket padding never changes a real
row. With ``fused=True`` (the default) each layer runs :mod:`.smolvla_kernels`' operations (≈ a third
of the kernels: fused projections and norms, rotary tables made once a sample, grouped-query
attention without per-head copies); with ``fused=False``, LeRobot's own in its order. The chunks
equal LeRobot's (``tests/policies/test_smolvla_static.py``: 1e-5 at every bucket in float32, RTC
too, fused or not; in LeRobot's order bit for bit with a bf16 SmolVLM beside a float32 expert, as
a real checkpoint loads, whose self-attention caches hold the promoted dtype LeRobot's
concatenation gives). Not done yet: ``--engine.compile_sampler``, and an expert with fewer layers
than the VLM (SmolVLA's default pairs them one to one).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from lerobot.policies.common.vla_utils import create_sinusoidal_pos_embedding, make_att_2d_masks
from torch import Tensor

from lerobot_armory.policies.cameras import served_cameras
from lerobot_armory.acceleration.pi05_kernels import KEY_ALIGN
from lerobot_armory.acceleration.pi05_static import FlowSchedule, SamplerInputs, policy_type
from lerobot_armory.acceleration.smolvla_kernels import SmolVLAFused, SmolVLAOrdered


class StaticSmolVLA:
    """``VLAFlowMatching.sample_actions`` without host synchronisation or per-step copies
    (arguments as :class:`~lerobot_armory.acceleration.pi05_static.StaticPi05`'s; ``attention`` must
    be ``eager``, LeRobot's own, and ``vision_dtype`` None; ``fused``: :mod:`.smolvla_kernels`
    where the policy allows it, :attr:`unfused_reason` says why not)."""

    kind = "smolvla"
    takes_state = True  # SmolVLA's state is a prefix token
    compilable = False  # --engine.compile_sampler: not yet

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
        if attention != "eager":
            raise ValueError(f"SmolVLA's static sampler runs LeRobot's own (eager) attention, got {attention!r}")
        if vision_dtype is not None:
            raise ValueError("SmolVLA's static sampler keeps the vision tower in the dtype it was loaded in")
        self.policy, self.model, self.config = policy, policy.model, policy.config
        self.vwe = self.model.vlm_with_expert
        vlm = self.vwe.get_vlm_model()
        self.text, self.expert, self.vision_model, self.connector = vlm.text_model, self.vwe.lm_expert, vlm.vision_model, vlm.connector
        self.guided = guided
        every = self.vwe.self_attn_every_n_layers
        cross = "cross" in self.vwe.attention_mode
        # LeRobot's SmolVLMWithExpertModel.forward: a layer is self-attention unless the mode is
        # cross-attention and the layer is not one of every n.
        self.self_attention = [not cross or (every > 0 and i % every == 0) for i in range(self.vwe.num_vlm_layers)]
        self.ops: SmolVLAFused | SmolVLAOrdered = SmolVLAOrdered(self.vwe, self.text)
        self.unfused_reason: str | None = None
        if fused:
            try:  # checks every layer before it touches a weight
                self.ops = SmolVLAFused(self.vwe, self.self_attention)
            except ValueError as exc:
                self.unfused_reason = str(exc)
        self.fused = isinstance(self.ops, SmolVLAFused)
        self.cameras = served_cameras(self.config)  # read once: a traced region cannot read config.type
        self.chunk_size = int(self.config.chunk_size)
        self.num_steps = int(self.config.num_steps)
        if self.num_steps < 1:
            raise ValueError(f"num_steps must be >= 1, got {self.num_steps}")
        device = next(self.model.parameters()).device
        schedule = FlowSchedule.make(self.num_steps, guided, max_guidance_weight, device)
        self.dt, self.times, self.time_table, self.guidance_table = schedule.dt, schedule.times, schedule.time_table, schedule.guidance_table
        # The suffix's actions attend causally (LeRobot's att_masks of ones).
        self.suffix_pattern = torch.ones(self.chunk_size, self.chunk_size, dtype=torch.bool, device=device).tril()
        self.no_keys = torch.zeros(1, self.chunk_size, KEY_ALIGN, dtype=torch.bool, device=device)  # the caches' padding, masked
        self.conditioning: tuple[Tensor, ...] | None = None  # prepare(): each step's time embedding
        self._constants: dict[str, Tensor] = {}

    @classmethod
    def unsupported_reason(cls, policy: Any) -> str | None:
        """Why this sampler cannot run ``policy`` (None: it can)."""
        config, model, kind = getattr(policy, "config", None), getattr(policy, "model", None), policy_type(policy)
        if kind != cls.kind:
            return f"{kind} is not {cls.kind}"
        vwe = getattr(model, "vlm_with_expert", None)
        parts = ("state_proj", "action_in_proj", "action_out_proj", "action_time_mlp_in", "action_time_mlp_out")
        if vwe is None or any(not hasattr(model, p) for p in parts):
            return f"{type(model).__name__} is not LeRobot 0.6's VLAFlowMatching"
        if not getattr(config, "use_cache", True):
            return "use_cache=false recomputes the prefix at every step: the static sampler caches it"
        if vwe.num_expert_layers != vwe.num_vlm_layers:
            return f"the expert has {vwe.num_expert_layers} layers for the VLM's {vwe.num_vlm_layers}: the static sampler pairs them one to one"
        if getattr(config, "n_obs_steps", 1) != 1:
            return "n_obs_steps > 1 stacks observations in the policy's queues"
        if getattr(config, "adapt_to_pi_aloha", False):
            return "adapt_to_pi_aloha converts the state and the actions around LeRobot's sampler"
        return None

    # -- the sampler ---------------------------------------------------------------------------

    @torch.no_grad()
    def prepare(self) -> tuple[Tensor, ...]:
        """Each step's time embedding ``(1, 1, W)``, the image scale and the special image tokens'
        embeddings, made once on the device (outside any traced or recorded region)."""
        if self.conditioning is not None:
            return self.conditioning
        m = self.model
        dtype = m.action_in_proj.weight.dtype  # LeRobot casts the time embedding to the actions'
        steps = []
        for step in range(self.num_steps):
            emb = create_sinusoidal_pos_embedding(
                self.time_table[step].expand(1), self.vwe.expert_hidden_size, self.config.min_period, self.config.max_period,
                device=self.time_table.device,
            )  # fmt: skip
            steps.append(emb.type(dtype=dtype)[:, None, :])
        device = self.time_table.device
        # LeRobot multiplies the image embeddings by a tensor of sqrt(width) in their dtype; made
        # here (a tensor from a Python number inside a recorded region is a host copy). The
        # connector's output width is the text model's: the prefix concatenates both.
        width = self.text.config.hidden_size
        self._constants["image_scale"] = torch.tensor(width**0.5, dtype=self._vision_out_dtype(), device=device)
        if m.add_image_special_tokens:
            self._constants["image_start"] = self.vwe.embed_language_tokens(m.global_image_start_token.to(device))
            self._constants["image_end"] = self.vwe.embed_language_tokens(m.image_end_token.to(device))
        self.conditioning = tuple(steps)
        return self.conditioning

    def compile_layers(self) -> None:
        raise ValueError("SmolVLA's static sampler is not compiled yet (--engine.compile_sampler=false)")

    def sample_compiled(self, inputs: SamplerInputs) -> Tensor:
        raise ValueError("SmolVLA's static sampler is not compiled yet (--engine.compile_sampler=false)")

    @torch.no_grad()
    def sample(self, inputs: SamplerInputs) -> Tensor:
        """Actions ``(B, chunk_size, max_action_dim)`` float32 for one batch (LeRobot's
        ``sample_actions`` given the same noise; the RTC guidance per row when ``guided``)."""
        return self.sample_embedded(inputs, self.vision(inputs.images))

    @torch.no_grad()
    def vision(self, images: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
        """What of the prefix depends on the images alone: each camera's embeddings (LeRobot's
        ``prepare_images`` and ``embed_image``, its empty cameras included), then each camera's
        mask (a graph of its own: ``BucketedSampler.start``)."""
        images, img_masks = self.policy.prepare_images(dict(zip(self.cameras, images, strict=True)))
        return (*self._embed_images(images), *img_masks)

    @torch.no_grad()
    def sample_embedded(self, inputs: SamplerInputs, vision: tuple[Tensor, ...]) -> Tensor:
        """:meth:`sample` given :meth:`vision`'s output for ``inputs.images`` (not read here)."""
        if self.guided != (inputs.rtc_weights is not None):
            raise ValueError("RTC inputs must be given exactly when the sampler is guided")
        if inputs.state is None:
            raise ValueError("SmolVLA's static sampler needs the state (SamplerInputs.state)")
        times = self.prepare()
        embs, pad, att = self._embed_prefix(inputs, vision)
        ops = self.ops
        b, p, h = pad.shape[0], pad.shape[1], self.chunk_size
        caches = self._prefix_cache(embs, pad, att)
        # A cross-attention layer's keys and values depend on the prefix alone: once a sample.
        cross = {i: ops.cross_kv(layer, caches[i], p) for i, layer in enumerate(self.expert.layers) if not self.self_attention[i]}
        parts = [pad[:, None, :].expand(b, h, p), self.suffix_pattern.expand(b, h, h)]
        gap = ops.cache_length(p, h) - p - h  # positions the ops' caches add after the suffix (masked)
        if gap:
            parts.append(self.no_keys[:, :, :gap].expand(b, h, gap))  # a view: no kernel
        valid = ops.additive(torch.cat(parts, dim=2))
        positions = pad.sum(dim=-1)[:, None] + torch.arange(h, device=pad.device)[None, :]
        # A cross-attention layer's queries count from 0 (LeRobot's positions minus their minimum).
        tables = ops.tables(positions), ops.tables(positions - torch.min(positions, dim=1, keepdim=True).values)
        x_t = inputs.noise
        for step, time in enumerate(self.times):
            v_t = self._velocity(x_t, times[step], caches, cross, valid, tables, p)
            x_t = self._guided_step(step, time, x_t, v_t, inputs)
        return x_t

    def _guided_step(self, step: int, time: Tensor, x_t: Tensor, v_t: Tensor, inputs: SamplerInputs) -> Tensor:
        """The Euler step, with RTC's closed-form guidance per row when guided."""
        if self.guided:
            assert self.guidance_table is not None and inputs.rtc_leftover is not None
            err = (inputs.rtc_leftover - (x_t - time * v_t)) * inputs.rtc_weights
            v_t = v_t - self.guidance_table[step] * err
        return x_t + self.dt * v_t

    def _prefix_cache(self, embs: Tensor, pad: Tensor, att: Tensor) -> list[tuple[Tensor, Tensor]]:
        """Run the VLM over the prefix; return per layer its keys and values (in :attr:`ops`'
        layout) with the prefix's post-rotary keys and values in the first ``P`` positions and
        room for the suffix's behind them."""
        ops = self.ops
        b, p = pad.shape
        mask = ops.additive(make_att_2d_masks(pad, att))
        table = ops.tables(torch.cumsum(pad, dim=1) - 1)
        caches = ops.caches(b, p, self.chunk_size, [self._cache_dtype(i) for i in range(len(self.text.layers))], embs.device)
        h = embs
        last = len(self.text.layers) - 1
        for i, layer in enumerate(self.text.layers):
            x = ops.norm(layer.input_layernorm, h).to(dtype=layer.self_attn.q_proj.weight.dtype)
            q = ops.self_attention_kv(layer, x, table, caches[i], 0)
            if i == last:  # the last layer's output is never read: only its keys and values are
                break
            h = ops.rest_of_layer(layer, h, ops.attend(q, *ops.prefix_kv(caches[i], p, x.dtype), mask))
        return caches

    def _velocity(
        self, x_t: Tensor, time_emb: Tensor, caches: list[Any], cross: dict[int, tuple[Tensor, Tensor]], valid: Tensor,
        tables: tuple[Any, Any], p: int,
    ) -> Tensor:  # fmt: skip
        """One denoising step (LeRobot's ``denoise_step``) through every expert layer (``valid``:
        the suffix queries' mask in :attr:`ops`' form, over the caches' positions; ``tables``: the
        rotary positions of the self-attention and the cross-attention queries; ``p``: the
        prefix's length, where the suffix's keys go)."""
        ops = self.ops
        m = self.model
        actions = m.action_in_proj(x_t)
        mixed = m.action_time_mlp_in(torch.cat([actions, time_emb.expand_as(actions)], dim=2))
        h = m.action_time_mlp_out(torch.nn.functional.silu(mixed))
        for i, layer in enumerate(self.expert.layers):
            x = ops.norm(layer.input_layernorm, h).to(dtype=layer.self_attn.q_proj.weight.dtype)
            if self.self_attention[i]:
                q = ops.self_attention_kv(layer, x, tables[0], caches[i], p)
                att = ops.attend(q, caches[i][0], caches[i][1], valid)
            else:
                att = ops.attend(ops.cross_query(layer, x, tables[1]), *cross[i], valid[..., :p])
            h = ops.rest_of_layer(layer, h, att)
        out = ops.norm(self.expert.norm, h)[:, -self.chunk_size :].to(dtype=torch.float32)
        return m.action_out_proj(out)

    def _cache_dtype(self, i: int) -> torch.dtype:
        """Layer i's K/V cache dtype: LeRobot concatenates the suffix's keys and values (the
        expert's dtype) onto the prefix's in a self-attention layer, promoting them."""
        k = self.text.layers[i].self_attn.k_proj.weight.dtype
        return torch.promote_types(k, self.expert.layers[i].self_attn.k_proj.weight.dtype) if self.self_attention[i] else k

    def _embed_prefix(self, inputs: SamplerInputs, vision: tuple[Tensor, ...]) -> tuple[Tensor, Tensor, Tensor]:
        """LeRobot's ``embed_prefix`` from :meth:`vision`'s output: (embeddings, pad mask,
        attention pattern ``att_masks``)."""
        from lerobot.policies.smolvla.modeling_smolvla import pad_tensor

        cameras = len(vision) // 2
        embs, pads, att_ones = [], [], []
        start, end = self._constants.get("image_start"), self._constants.get("image_end")
        for image_emb, img_mask in zip(vision[:cameras], vision[cameras:], strict=True):
            b, device = image_emb.shape[0], image_emb.device
            if start is not None:
                embs.append(start.unsqueeze(0).expand(b, -1, -1))
                pads.append(torch.ones(b, start.shape[0], dtype=torch.bool, device=device))
            emb = image_emb * self._constants["image_scale"]
            embs.append(emb)
            pads.append(img_mask[:, None].expand(b, emb.shape[1]))
            if end is not None:
                embs.append(end.unsqueeze(0).expand(b, -1, -1))
                pads.append(torch.ones(b, end.shape[0], dtype=torch.bool, device=device))
        lang = self.vwe.embed_language_tokens(inputs.tokens)
        embs.append(lang * math.sqrt(lang.shape[-1]))
        pads.append(inputs.masks)
        state = self.model.state_proj(inputs.state)
        state = state[:, None, :] if state.ndim == 2 else state
        embs.append(state)
        pads.append(torch.ones(state.shape[0], state.shape[1], dtype=torch.bool, device=state.device))
        att_ones.append(state.shape[1])
        embs_t, pad_t = torch.cat(embs, dim=1), torch.cat(pads, dim=1)
        length = pad_t.shape[1]
        # Images and language: 0 (attend each other); the state tokens: 1 (they attend everything
        # before them, nothing before attends them); LeRobot's padding to prefix_length: 0.
        # (Compared, not assigned: ``att[i:] = True`` makes a tensor of the Python bool, a host copy.)
        att = (torch.arange(length, device=pad_t.device) >= length - att_ones[0])[None, :]
        target = self.ops.prefix_length(length, self.model.prefix_length)
        if length < target:
            embs_t = pad_tensor(embs_t, target, pad_value=0)
            pad_t = pad_tensor(pad_t, target, pad_value=0)
            att = pad_tensor(att, target, pad_value=0)
        return embs_t, pad_t, att.expand(pad_t.shape[0], -1)

    def _embed_images(self, images: list[Tensor]) -> list[Tensor]:
        """Each camera's image embeddings; cameras of one shape pass the vision tower as one batch
        (LeRobot runs it once per camera: rows never mix, so the values are the same, with half
        the vision kernels for two cameras)."""
        if len(images) > 1 and len({img.shape for img in images}) == 1:
            return list(self._embed_image(torch.cat(images, dim=0)).chunk(len(images), dim=0))
        return [self._embed_image(img) for img in images]

    def _embed_image(self, pixels: Tensor) -> Tensor:
        """LeRobot's ``embed_image`` (HF's SmolVLM vision transformer and connector) for full patch
        masks, with the position ids computed from the shape alone."""
        vision = self.vision_model
        pixels = pixels.to(dtype=vision.dtype)
        emb = vision.embeddings
        x = emb.patch_embedding(pixels).flatten(2).transpose(1, 2)
        x = x + emb.position_embedding(self._position_ids(pixels))
        x = vision.encoder(inputs_embeds=x, attention_mask=None).last_hidden_state
        return self.connector(vision.post_layernorm(x))

    def _position_ids(self, pixels: Tensor) -> Tensor:
        """HF's ``SmolVLMVisionEmbeddings`` position ids for a full patch mask (every patch
        valid), by its own formula: the boolean-mask write that follows it is then the identity."""
        emb = self.vision_model.embeddings
        b, _, height, width = pixels.shape
        rows, cols = height // emb.patch_size, width // emb.patch_size
        side = emb.num_patches_per_side
        boundaries = torch.arange(1 / side, 1.0, 1 / side, device=pixels.device)
        coords = []
        for n in (rows, cols):
            frac = torch.arange(n, device=pixels.device, dtype=torch.float32) * (1.0 / n)
            coords.append(torch.bucketize(torch.clamp(frac, max=(1.0 - 1e-6)).to(pixels.dtype), boundaries, right=True))
        ids = coords[0][:, None] * side + coords[1][None, :]
        return ids.reshape(1, -1).expand(b, -1)

    def _vision_out_dtype(self) -> torch.dtype:
        """The dtype of the image embeddings LeRobot scales (the connector's output)."""
        return next(self.connector.parameters()).dtype
