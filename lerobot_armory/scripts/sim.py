"""``lerobot-armory-sim``: one simulated fleet under one scheduler."""

from __future__ import annotations

from lerobot_armory.sim.cli import main as _main


def main(argv: list[str] | None = None) -> None:
    """``lerobot-armory-sim`` (``--help`` lists its options)."""
    _main(argv)


if __name__ == "__main__":
    main()
