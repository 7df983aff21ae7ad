"""``lerobot-armory-server``: serve a policy to a fleet of robots (gRPC, optionally openpi)."""

from __future__ import annotations

from lerobot_armory.entrypoints.server import main as _main


def main(argv: list[str] | None = None) -> None:
    """``lerobot-armory-server`` (``--help`` lists its options)."""
    _main(argv)


if __name__ == "__main__":
    main()
