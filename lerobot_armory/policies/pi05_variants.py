"""Tiny Gemma sizes for LeRobot's own π0.5, π0 and π0-FAST classes (``paligemma_variant="armory_tiny"``).

LeRobot 0.6 sizes π0.5, π0 and π0-FAST by *named* Gemma variants only (``gemma_300m``, ``gemma_2b``:
``modeling_pi05.get_gemma_config`` / ``modeling_pi0.get_gemma_config``, checked in
``PI05Config.__post_init__`` / ``PI0Config.__post_init__``), and the PaliGemma wrapper hard-codes
the SigLIP vision tower (≈ 400 M parameters) and the 257 152-token vocabulary. Nothing of that
size runs a batch on a laptop CPU in seconds, which the tests and the offline demo need.
:func:`register` adds more named variants, ``armory_tiny`` and ``armory_narrow``, to the *same*
classes (``PI05Config``, ``PI05Policy``, ``PI05Pytorch``, ``PaliGemmaWithExpertModel``, their
π0 twins ``PI0Config``, ``PI0Policy``, ``PI0Pytorch`` and π0-FAST's ``PI0FastConfig``,
``PI0FastPolicy``, ``PI0FastPytorch``): the same code path runs — prefix encoding, KV cache,
10 flow-matching steps, the action expert, RTC hooks (π0-FAST: autoregressive decoding) — only
the widths, depths, the vision tower and the vocabulary are small.

How: narrow patches of each of ``lerobot.policies.pi05``, ``lerobot.policies.pi0`` and
``lerobot.policies.pi0_fast`` (the modules name these functions and classes alike), each a no-op
unless a variant of ours is being built (a ``ContextVar`` set while ``PI05Pytorch.__init__``,
``PI0Pytorch.__init__`` or ``PI0FastPytorch.__init__`` runs),
so the real variants and hub checkpoints load exactly as LeRobot loads them:

- the configs' ``__post_init__`` accept the variant names of :data:`VARIANTS`;
- ``get_gemma_config`` returns their Gemma sizes;
- the PaliGemma and expert constructors get a small SigLIP config (projection to the text width,
  images of ``image_resolution``) and a small vocabulary (:data:`TINY_VOCAB`; the stand-in
  tokenizer's ids all fit in it; π0-FAST's is its text tokenizer's, whose top ids are its action
  tokens).

A process that loads such a policy directory must call :func:`register` first; the server does
(``engine/policy_engine.py``), and so must any plain LeRobot script that loads one
(``import lerobot_armory.policies.pi05_variants as v; v.register()``).
"""

from __future__ import annotations

import contextvars
import threading
from dataclasses import dataclass
from typing import Any

TINY = "armory_tiny"
# LeRobot's real layer counts (18 Gemma layers in the VLM and in the expert, 27 SigLIP layers,
# 8 query heads on 1 K/V head, 256 image tokens per 224² camera) at tiny widths: a model whose
# forward pass launches as many kernels as the real π0.5's, which a CPU runs in a second.
NARROW = "armory_narrow"
# Vocabulary of the tiny variant: the stand-in tokenizer (``demo/standin_tokenizer.py``) has
# fewer pieces, so every id it emits is inside the model's embedding table.
TINY_VOCAB = 1024


@dataclass(frozen=True)
class VisionSize:
    """SigLIP sizes of a variant (the real π0.5 uses So400m: 1152 wide, 27 layers, patch 14)."""

    hidden_size: int
    num_hidden_layers: int
    num_attention_heads: int
    intermediate_size: int
    patch_size: int


@dataclass(frozen=True)
class Variant:
    """Sizes of one registered variant: Gemma (as openpi's ``gemma.get_config``), vision, vocab."""

    width: int
    depth: int
    mlp_dim: int
    num_heads: int
    num_kv_heads: int
    head_dim: int
    vision: VisionSize
    vocab_size: int


VARIANTS: dict[str, Variant] = {
    TINY: Variant(
        width=64, depth=2, mlp_dim=128, num_heads=2, num_kv_heads=1, head_dim=32,
        vision=VisionSize(hidden_size=32, num_hidden_layers=1, num_attention_heads=2, intermediate_size=64, patch_size=8),
        vocab_size=TINY_VOCAB,
    ),
    NARROW: Variant(
        width=64, depth=18, mlp_dim=128, num_heads=8, num_kv_heads=1, head_dim=16,
        vision=VisionSize(hidden_size=32, num_hidden_layers=27, num_attention_heads=2, intermediate_size=64, patch_size=14),
        vocab_size=TINY_VOCAB,
    ),
}  # fmt: skip

@dataclass(frozen=True)
class _Build:
    """What the patched constructors need while a model of ours is being built."""

    variant: Variant
    image_size: int  # the config's image_resolution (π0-FAST would leave SigLIP at its 224 default)
    vocab_size: int  # the variant's; π0-FAST's text tokenizer's (its action ids count down from the top)


# The model of ours being built in this thread (None: a LeRobot variant, untouched).
_building: contextvars.ContextVar[_Build | None] = contextvars.ContextVar("armory_pi_variant", default=None)
_lock = threading.Lock()
_registered = False


# LeRobot policy types whose modules are patched: type -> (modeling module, config module and
# class, core model class), all named alike.
PATCHED_TYPES = {
    "pi05": ("lerobot.policies.pi05.modeling_pi05", "lerobot.policies.pi05.configuration_pi05", "PI05Config", "PI05Pytorch"),
    "pi0": ("lerobot.policies.pi0.modeling_pi0", "lerobot.policies.pi0.configuration_pi0", "PI0Config", "PI0Pytorch"),
    "pi0_fast": (
        "lerobot.policies.pi0_fast.modeling_pi0_fast", "lerobot.policies.pi0_fast.configuration_pi0_fast",
        "PI0FastConfig", "PI0FastPytorch",
    ),
}  # fmt: skip


def register() -> None:
    """Make LeRobot's π0.5, π0 and π0-FAST accept the variants of :data:`VARIANTS` (idempotent, thread-safe).

    Raises:
        ImportError: ``transformers`` (LeRobot's ``pi`` extra) is not installed.
    """
    global _registered
    with _lock:
        if _registered:
            return
        import importlib

        modules = []
        for modeling, configuration, config_cls, model_cls in PATCHED_TYPES.values():
            m = importlib.import_module(modeling)
            if m.PaliGemmaForConditionalGenerationWithPiGemma is None:
                raise ImportError("π0, π0.5 and π0-FAST need transformers: pip install 'lerobot-armory[pi]'")
            modules.append((m, getattr(importlib.import_module(configuration), config_cls), getattr(m, model_cls)))
        for m, config_cls, model_cls in modules:  # all importable: patch them all or none
            _patch_config(config_cls)
            _patch_model(m, model_cls)
        _registered = True


def _patch_config(config_cls: Any) -> None:
    validate = config_cls.__post_init__
    fields = ("paligemma_variant", "action_expert_variant")

    def __post_init__(self: Any) -> None:  # noqa: N807 - replaces the dataclass hook
        # LeRobot validates against a literal list of its own names; let ours through that one
        # check and restore them right after, so everything else it validates still runs.
        ours = {f: getattr(self, f) for f in fields if getattr(self, f, None) in VARIANTS}
        for f in ours:
            setattr(self, f, "gemma_300m")
        try:
            validate(self)
        finally:
            for f, name in ours.items():
                setattr(self, f, name)

    config_cls.__post_init__ = __post_init__


def _patch_model(m: Any, model_cls: Any) -> None:
    get_config = m.get_gemma_config
    build_vlm = m.PaliGemmaForConditionalGenerationWithPiGemma
    build_expert = getattr(m, "PiGemmaForCausalLM", None)  # π0-FAST has no action expert
    init_model = model_cls.__init__

    def get_gemma_config(variant: str) -> Any:
        v = VARIANTS.get(variant)
        if v is None:
            return get_config(variant)
        return m.GemmaConfig(v.width, v.depth, v.mlp_dim, v.num_heads, v.num_kv_heads, v.head_dim)

    def vlm(config: Any) -> Any:
        b = _building.get()
        if b is not None:
            v = b.variant
            vis = config.vision_config
            vis.hidden_size = v.vision.hidden_size
            vis.num_hidden_layers = v.vision.num_hidden_layers
            vis.num_attention_heads = v.vision.num_attention_heads
            vis.intermediate_size = v.vision.intermediate_size
            vis.patch_size = v.vision.patch_size
            vis.image_size = b.image_size
            # Image tokens join the text sequence: project to the text width (LeRobot fixes
            # 2048, the width of gemma_2b, the only PaliGemma size it ships).
            vis.projection_dim = config.text_config.hidden_size
            config.text_config.vocab_size = b.vocab_size
        return build_vlm(config=config)

    def expert(config: Any) -> Any:
        b = _building.get()
        if b is not None:
            config.vocab_size = b.vocab_size  # the expert's embedding is dropped; its lm_head is unused
        return build_expert(config=config)

    def __init__(self: Any, config: Any, *args: Any, **kwargs: Any) -> None:  # noqa: N807
        v = VARIANTS.get(config.paligemma_variant)
        if v is not None and config.image_resolution[0] % v.vision.patch_size:
            raise ValueError(
                f"image_resolution {config.image_resolution} must be a multiple of the {config.paligemma_variant} "
                f"patch size {v.vision.patch_size}"
            )
        build = None
        if v is not None:
            # π0-FAST maps its action tokens from the top of the text tokenizer's vocabulary
            # (``vocab_size - 1 - fast_skip_tokens - token``), so its model's vocabulary is the
            # tokenizer's, as PaliGemma's is.
            tokenizer = kwargs.get("paligemma_tokenizer")
            vocab = v.vocab_size if tokenizer is None else tokenizer.vocab_size
            build = _Build(v, config.image_resolution[0], vocab)
        token = _building.set(build)
        try:
            init_model(self, config, *args, **kwargs)
        finally:
            _building.reset(token)

    m.get_gemma_config = get_gemma_config
    m.PaliGemmaForConditionalGenerationWithPiGemma = vlm
    if build_expert is not None:
        m.PiGemmaForCausalLM = expert
    model_cls.__init__ = __init__


def uses_variant(config_json: dict[str, Any]) -> bool:
    """True if a saved ``config.json`` names a variant of ours (the loader must :func:`register`)."""
    return config_json.get("paligemma_variant") in VARIANTS or config_json.get("action_expert_variant") in VARIANTS
