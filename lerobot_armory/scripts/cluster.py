"""``lerobot-armory-cluster``: serve from a Ray cluster of replicas behind one front."""

from __future__ import annotations

from lerobot_armory.entrypoints.cluster.cli import main as _main


def main(argv: list[str] | None = None) -> None:
    """``lerobot-armory-cluster`` (``--help`` lists its options)."""
    _main(argv)


if __name__ == "__main__":
    main()
