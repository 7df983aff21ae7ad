"""``lerobot-armory-sweep``: the reference sweep in the simulator (CSV, JSON, figures)."""

from __future__ import annotations

from lerobot_armory.sim.sweep import main as _main


def main(argv: list[str] | None = None) -> None:
    """``lerobot-armory-sweep`` (``--help`` lists its options)."""
    _main(argv)


if __name__ == "__main__":
    main()
