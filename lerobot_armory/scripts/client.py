"""``lerobot-armory-client``: run one robot against a server (any LeRobot robot, PiPER, armory_sim, MetaWorld)."""

from __future__ import annotations

from lerobot_armory.robot.cli import main as _main


def main(argv: list[str] | None = None) -> None:
    """``lerobot-armory-client`` (``--help`` lists its options)."""
    _main(argv)


if __name__ == "__main__":
    main()
