"""``lerobot-armory-bench``: the live server against the simulator's prediction, per scheduler."""

from __future__ import annotations

from lerobot_armory.bench.live import main as _main


def main(argv: list[str] | None = None) -> None:
    """``lerobot-armory-bench`` (``--help`` lists its options)."""
    _main(argv)


if __name__ == "__main__":
    main()
