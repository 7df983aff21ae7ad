"""``lerobot-armory-make-demo-policy``: build a demo policy offline (random weights), loadable as --policy.path."""

from __future__ import annotations

from lerobot_armory.demo.build import main as _main


def main(argv: list[str] | None = None) -> None:
    """``lerobot-armory-make-demo-policy`` (``--help`` lists its options)."""
    _main(argv)


if __name__ == "__main__":
    main()
