"""Every robot type ``lerobot-armory-client`` can drive, found rather than listed.

``--robot.type`` is a draccus choice: only robot config classes that were *imported* before the
command line is parsed are choices. LeRobot's own scripts import their robots by hand (a fixed
list in ``lerobot/async_inference/robot_client.py``); here the ``lerobot.robots`` package is
walked instead, so a newer LeRobot's robots appear by themselves. Then come third-party
``lerobot_robot_*`` plugins (LeRobot's ``register_third_party_plugins()``), then the robots shipped
here (``armory_sim``, ``piper``, ``metaworld``). LeRobot's camera configs are found the same way, so
``--robot.cameras='{"wrist": {"type": "opencv", ...}}'`` parses for every robot.
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import pkgutil

from lerobot.robots.config import RobotConfig

log = logging.getLogger(__name__)

#: Packages walked for config modules: every subpackage's ``config*`` modules are imported.
LEROBOT_PACKAGES: tuple[str, ...] = ("lerobot.robots", "lerobot.cameras")
#: The robot types shipped with lerobot-armory (imported last: a plugin may not be shadowed by us).
OWN_CONFIG_MODULES: tuple[str, ...] = (
    "lerobot_armory.robot.armory_sim.config_armory_sim",
    "lerobot_armory.robot.piper.config_piper",
    "lerobot_armory.robot.metaworld.config_metaworld",
)

#: ``{module: reason}`` of everything that could not be imported by the last registration
#: (logged at debug level once ``--log_level`` is known; the rest still works).
SKIPPED: dict[str, str] = {}


def register_robot_types() -> None:
    """Make every robot type and camera type selectable; idempotent, never raises."""
    for package in LEROBOT_PACKAGES:
        _import_config_modules(package)
    try:
        from lerobot.utils.import_utils import register_third_party_plugins

        register_third_party_plugins()  # logs (and survives) a broken plugin itself
    except Exception as exc:  # an older LeRobot without it, or a plugin that kills the scan
        _skip("third-party plugins", exc)
    for module in OWN_CONFIG_MODULES:
        _import(module)


def robot_types() -> list[str]:
    """Every registered ``--robot.type``, sorted."""
    return sorted(RobotConfig.get_known_choices())


def lerobot_robot_types() -> list[str]:
    """The registered robot types whose config LeRobot itself ships, sorted."""
    return sorted(
        name for name, cls in RobotConfig.get_known_choices().items() if cls.__module__.startswith("lerobot.robots.")
    )


def _import_config_modules(package: str) -> None:
    """Import the ``config*`` modules of every subpackage of ``package`` (the subpackage itself
    when it has none: a layout LeRobot may adopt later still registers through its ``__init__``)."""
    try:
        root = importlib.import_module(package)
    except Exception as exc:
        _skip(package, exc)
        return
    for sub in pkgutil.iter_modules(root.__path__, f"{package}."):
        if not sub.ispkg:
            continue
        # Found without importing the subpackage, so one config module failing spares its siblings.
        spec = importlib.util.find_spec(sub.name)
        locations = list(spec.submodule_search_locations or []) if spec is not None else []
        configs = [
            m.name
            for m in pkgutil.iter_modules(locations, f"{sub.name}.")
            if m.name.rpartition(".")[2].startswith("config")
        ]
        for module in configs or [sub.name]:
            _import(module)


def _import(module: str) -> None:
    try:
        importlib.import_module(module)
    except Exception as exc:  # a robot whose import fails must not take the other robots down
        _skip(module, exc)


def _skip(what: str, exc: Exception) -> None:
    reason = f"{type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}"
    SKIPPED[what] = reason
    # A missing optional package is normal (that robot's SDK is not installed); anything else is
    # worth a warning, e.g. two packages registering the same robot type name.
    log.log(logging.DEBUG if isinstance(exc, ImportError) else logging.WARNING, "skipped %s (%s)", what, reason)
