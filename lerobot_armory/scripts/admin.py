"""``lerobot-armory-admin``: the operator's client: swap a checkpoint, read a server's status."""

from __future__ import annotations

from lerobot_armory.entrypoints.admin import main as _main


def main(argv: list[str] | None = None) -> None:
    """``lerobot-armory-admin`` (``--help`` lists its options)."""
    _main(argv)


if __name__ == "__main__":
    main()
