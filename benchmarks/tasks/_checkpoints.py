"""The committed MetaWorld checkpoints every task benchmark runs (examples/checkpoints/README.md)."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CHECKPOINTS = {
    "push": ROOT / "examples/checkpoints/metaworld-push-act",
    "reach-moving": ROOT / "examples/checkpoints/metaworld-reach-moving-act",
}
