"""``lerobot-armory-status``: a running server's fleet, one line per robot."""

from __future__ import annotations

from lerobot_armory.entrypoints.status import main as _main


def main(argv: list[str] | None = None) -> None:
    """``lerobot-armory-status`` (``--help`` lists its options)."""
    _main(argv)


if __name__ == "__main__":
    main()
