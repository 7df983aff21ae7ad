"""Discrete-event fleet simulator (docs/spec.md §5): the real mirror and schedulers on simulated time."""

from lerobot_armory.network_delay import LogNormalDelay
from lerobot_armory.sim.presets import MIXES, PRESETS, Preset, fleet_specs, get_preset
from lerobot_armory.sim.simulator import FleetSimulator, RobotResult, SimResult

__all__ = [
    "MIXES",
    "PRESETS",
    "FleetSimulator",
    "LogNormalDelay",
    "Preset",
    "RobotResult",
    "SimResult",
    "fleet_specs",
    "get_preset",
]
