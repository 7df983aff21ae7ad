"""``lerobot-armory-tasks``: task success of a trained policy on MetaWorld: local, served, openpi."""

from __future__ import annotations

from lerobot_armory.bench.tasks import main as _main


def main(argv: list[str] | None = None) -> None:
    """``lerobot-armory-tasks`` (``--help`` lists its options)."""
    _main(argv)


if __name__ == "__main__":
    main()
