"""Build a π0 policy directory offline: LeRobot's ``PI0Config`` / ``PI0Policy`` with random
weights, LeRobot's own π0 pre/post-processors, and a stand-in tokenizer stored inside it.

    lerobot-armory-make-demo-policy --kind=pi0 --output=out/pi0-tiny
    lerobot-armory-server --policy.path=out/pi0-tiny

The same build as π0.5's (:mod:`.pi05`, which holds the shared code): LeRobot's π0 ships only the
``gemma_2b``/``gemma_300m`` sizes with SigLIP So400m, so ``size=tiny`` (the default) and
``size=narrow`` use the Gemma variants :mod:`lerobot_armory.policies.pi05_variants` registers for
π0 as for π0.5 (``armory_tiny``: 0.4 M parameters); ``size=full`` is the real π0 (3.3 B).
The paligemma tokenizer (gated on the hub) is stood in by ``DIR/tokenizer``, which the server
points the pre-processor's ``tokenizer_processor`` step at wherever the directory has moved.
Unlike π0.5, π0 projects the state with a linear layer (the prompt is the task alone) and
normalises by mean/std.

π0 is a flow-matching policy whose ``predict_action_chunk(batch, noise=...)`` passes the initial
noise ``(B, chunk_size, 32)`` through to its sampler: the same noise gives the same chunk.
A process that loads the directory registers the variants first (the server does;
``lerobot_armory.policies.pi05_variants.register()`` in a plain LeRobot script).
"""

from __future__ import annotations

from pathlib import Path

from lerobot_armory.demo.pi05 import make_pi_policy


def make_pi0_policy(
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
    """Build and save a random-weight π0; returns its directory (arguments as
    :func:`lerobot_armory.demo.pi05.make_pi05_policy`)."""
    return make_pi_policy("pi0", output, size, chunk_size, state_dim, action_dim, cameras, image_size, seed, dtype, device)
