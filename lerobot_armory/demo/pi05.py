"""Build a π0.5 policy directory offline: LeRobot's ``PI05Config`` / ``PI05Policy`` with random
weights, LeRobot's own π0.5 pre/post-processors, and a stand-in tokenizer stored inside it.

    lerobot-armory-make-demo-policy --kind=pi05 --size=tiny --output=out/pi05-tiny
    lerobot-armory-server --policy.path=out/pi05-tiny

``size=full`` is the real architecture (PaliGemma ``gemma_2b`` + SigLIP So400m at 224², expert
``gemma_300m``: 4.1 B parameters; 9.4 GB on disk with ``--dtype=bfloat16``, whose vision tower
LeRobot keeps in float32; building it peaks at 19 GB of RAM);
``size=tiny`` is the same classes and code path at the registered ``armory_tiny`` Gemma size
(``policies/pi05_variants.py``; 0.4 M parameters, a batch of 8 in well under a second on a CPU);
``size=narrow`` has the real π0.5's depths, heads, image size and prompt length at tiny widths
(``armory_narrow``: as many kernels per forward pass as the real model, for counting them).

The input features are ``observation.state`` and one ``observation.images.<camera>`` per camera,
as ``armory_sim`` sends them, so simulated robots can be served by it. The directory loads with
``--policy.path=DIR`` and no network: the pre-processor's tokenizer step names the stand-in in
``DIR/tokenizer`` (the server always points it there, so the directory can be moved).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from lerobot_armory.errors import ConfigError
from lerobot_armory.demo.common import policy_features
from lerobot_armory.policies.layout import TOKENIZER_DIR  # where the loader looks for it

SIZES = ("tiny", "narrow", "full")


def make_pi05_policy(
    output: str | Path,
    size: str = "tiny",
    chunk_size: int = 50,
    state_dim: int = 2,
    action_dim: int | None = None,
    cameras: tuple[str, ...] = ("front",),
    image_size: int = 64,
    seed: int = 0,
    dtype: str = "float32",
    device: str = "cpu",
) -> Path:
    """Build and save a random-weight π0.5; returns its directory.

    Args:
        output: directory to write (created).
        size: ``tiny`` (registered ``armory_tiny`` variant), ``narrow`` (``armory_narrow``: full
            depth, tiny width) or ``full`` (gemma_2b + gemma_300m).
        chunk_size: H, actions per chunk (π0.5's default is 50).
        state_dim / action_dim: vector sizes (padded internally to π0.5's 32).
        cameras: camera names; each becomes ``observation.images.<name>`` of ``image_size``².
        image_size: side of the images robots send (the model resizes to its own resolution).
        seed: torch seed for the random weights.
        dtype: ``float32`` or ``bfloat16`` weights (LeRobot keeps the vision tower in float32).
        device: where the random weights are created (``cuda`` builds the full size in seconds
            where a CPU takes minutes); they are saved the same way, and the saved config names
            the CPU as LeRobot's own builds do.
    """
    return make_pi_policy(
        "pi05", output, size, chunk_size, state_dim, action_dim, cameras, image_size, seed, dtype, device
    )


# What differs between the π types built here: LeRobot's module and class names, the prompt
# length (π0.5 writes the discretised state into the prompt; π0 sends the task alone).
_PI_TYPES = {
    # type: (display name, package, config class, policy class, prompt length tiny, full)
    "pi05": ("π0.5", "pi05", "PI05Config", "PI05Policy", 64, 200),
    "pi0": ("π0", "pi0", "PI0Config", "PI0Policy", 32, 48),
}


def make_pi_policy(
    policy_type: str,
    output: str | Path,
    size: str = "tiny",
    chunk_size: int = 50,
    state_dim: int = 2,
    action_dim: int | None = None,
    cameras: tuple[str, ...] = ("front",),
    image_size: int = 64,
    seed: int = 0,
    dtype: str = "float32",
    device: str = "cpu",
) -> Path:
    """:func:`make_pi05_policy` for ``policy_type`` ``pi05`` or ``pi0`` (same arguments)."""
    import importlib

    import torch
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_armory.policies import pi05_variants
    from lerobot_armory.demo.standin_tokenizer import build_standin_tokenizer

    name, package, config_name, policy_name, tiny_prompt, full_prompt = _PI_TYPES[policy_type]
    if size not in SIZES:
        raise ConfigError("size", f"must be one of {', '.join(SIZES)}, got {size!r}")
    if dtype not in ("float32", "bfloat16"):
        raise ConfigError("dtype", f"must be float32 or bfloat16, got {dtype!r}")
    inputs, outputs = policy_features(name, chunk_size, state_dim, action_dim, cameras, image_size, max_dim=32)
    try:
        pi05_variants.register()
        config_cls = getattr(importlib.import_module(f"lerobot.policies.{package}.configuration_{package}"), config_name)
        policy_cls = getattr(importlib.import_module(f"lerobot.policies.{package}.modeling_{package}"), policy_name)
        processor_module = importlib.import_module(f"lerobot.policies.{package}.processor_{package}")
    except ImportError as exc:
        raise ConfigError("kind", f"{name} needs LeRobot's pi extra (pip install 'lerobot-armory[pi]'): {exc}") from None
    tiny = size == "tiny"
    variant = {"tiny": pi05_variants.TINY, "narrow": pi05_variants.NARROW}.get(size)
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    vocab = pi05_variants.TINY_VOCAB if variant else 257152
    tokenizer = build_standin_tokenizer(out / TOKENIZER_DIR, max_id=vocab)
    config = config_cls(
        paligemma_variant=variant or "gemma_2b",
        action_expert_variant=variant or "gemma_300m",
        image_resolution=(32, 32) if tiny else (224, 224),
        tokenizer_max_length=tiny_prompt if tiny else full_prompt,
        chunk_size=chunk_size,
        n_action_steps=chunk_size,
        dtype=dtype,
        input_features=inputs,
        output_features=outputs,
        device="cpu",
    )
    torch.manual_seed(seed)
    config.device = device
    with torch.device(device):
        policy = policy_cls(config)
    config.device = "cpu"  # what the saved config and processors name; the loader picks its own
    # π0.5 normalises state and action by quantiles, π0 by mean/std; armory_sim's positions live
    # in [-1, 1].
    stats = {
        "observation.state": _unit_stats(inputs["observation.state"].shape[0]),
        "action": _unit_stats(outputs["action"].shape[0]),
    }
    with _tokenizer_from(tokenizer, processor_module):
        pre, post = make_pre_post_processors(config, dataset_stats=stats)
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    return out


def _unit_stats(dim: int) -> dict:
    import torch

    ones = torch.ones(dim)
    return {"q01": -ones, "q99": ones, "min": -ones, "max": ones, "mean": 0 * ones, "std": ones}


@contextlib.contextmanager
def _tokenizer_from(path: Path, processor_module: Any) -> Iterator[None]:
    """While building the pre-processor, the tokenizer step of LeRobot's π0.5 (or π0:
    ``processor_module``) loads ``path`` instead of the gated hub tokenizer (the saved step then
    names ``path``)."""
    real = processor_module.TokenizerProcessorStep

    def step(**kwargs):
        kwargs["tokenizer_name"] = str(path.resolve())
        return real(**kwargs)

    processor_module.TokenizerProcessorStep = step
    try:
        yield
    finally:
        processor_module.TokenizerProcessorStep = real
