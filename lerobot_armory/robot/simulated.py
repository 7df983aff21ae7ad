"""What every simulated robot shares as a LeRobot ``Robot``."""

from __future__ import annotations

from lerobot.robots.robot import Robot


class SimulatedRobot(Robot):
    """A LeRobot ``Robot`` with no hardware: nothing to calibrate or configure."""

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        """Nothing to calibrate in simulation."""

    def configure(self) -> None:
        """Nothing to configure in simulation."""
