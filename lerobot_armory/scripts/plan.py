"""``lerobot-armory-plan``: capacity planning: how many GPUs a fleet needs."""

from __future__ import annotations

from lerobot_armory.sim.plan import main as _main


def main(argv: list[str] | None = None) -> None:
    """``lerobot-armory-plan`` (``--help`` lists its options)."""
    _main(argv)


if __name__ == "__main__":
    main()
