"""One line instead of a traceback when a robot's hardware is missing or stops answering.

LeRobot's robots fail in layers: a motor bus wraps the serial error in a multi-line
``ConnectionError`` ("Could not connect on port ...", its ``__cause__`` the ``SerialException``
that says *why*), a missing motor is a ``RuntimeError`` listing expected and found ids, a missing
SDK is an ``ImportError`` from ``require_package`` that names the pip extra, and a robot built
through ``make_device_from_device_class`` arrives wrapped in ``ValueError("Error creating robot
with config <repr>: ...")``. :func:`explain_robot_error` walks that chain and names the robot,
its port and the reason, with what to do about it.
"""

from __future__ import annotations

import errno
import re
from collections.abc import Iterator

from lerobot.robots.config import RobotConfig
from lerobot.utils.errors import DeviceNotConnectedError

#: Config fields that say where a robot is, in the order they are looked for.
ADDRESS_FIELDS: tuple[str, ...] = ("port", "can_port", "remote_ip", "ip_address", "ip", "host")
#: Nested arm configs of bimanual robots (``bi_so_follower``, ``bi_openarm_follower``, ...).
ARM_FIELDS: tuple[str, ...] = ("left_arm_config", "right_arm_config")

_PORT_IN_TEXT = re.compile(r"port '([^']+)'")
_MISSING_IDS = re.compile(r"^\s*-\s*(\d+)\s*\(expected model", re.MULTILINE)
# What a Feetech/Dynamixel SDK says when a motor does not reply (TxRxResult texts).
_NO_REPLY = ("no status packet", "rx timeout", "rx_timeout", "incorrect status packet", "rx corrupt", "was not found")


class RobotUnavailable(RuntimeError):
    """The robot could not be built, connected or driven; the message is one line for the user."""


def explain_robot_error(exc: BaseException, cfg: RobotConfig, robot_type: str | None = None) -> str:
    """``robot <type> on <port>: <reason>`` in one line, for any exception a robot raised.

    ``robot_type`` is the name the user typed (default ``cfg.type``, which names only the first
    of a config class's registered names).
    """
    chain = list(_chain(exc))
    where = _where(chain, cfg)
    kind = robot_type or cfg.type
    return f"robot {kind}{f' on {where}' if where else ''}: {_reason(chain, kind, where)}"


def robot_address(cfg: RobotConfig) -> str | None:
    """Where the robot is (serial/CAN port, IP), from its config; bimanual robots list both arms."""
    for name in ADDRESS_FIELDS:
        value = getattr(cfg, name, None)
        if isinstance(value, str) and value:
            return value
    arms = [getattr(getattr(cfg, arm, None), "port", None) for arm in ARM_FIELDS]
    arms = [a for a in arms if isinstance(a, str) and a]
    return " and ".join(arms) or None


def _chain(exc: BaseException) -> Iterator[BaseException]:
    """The exception, then its causes (``raise ... from``) and contexts, outermost first."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        yield current
        current = current.__cause__ or current.__context__


def _where(chain: list[BaseException], cfg: RobotConfig) -> str | None:
    # The port named in the error wins: of a bimanual robot's two ports it is the one that failed.
    for e in chain:
        found = _PORT_IN_TEXT.search(str(e))
        if found:
            return found.group(1)
    return robot_address(cfg)


def _first_line(e: BaseException) -> str:
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return lines[0] if lines else type(e).__name__


def _reason(chain: list[BaseException], robot_type: str, where: str | None) -> str:
    port = where or "the port"
    if type(chain[0]).__module__.startswith("lerobot_armory."):
        return _first_line(chain[0])  # our own adapters (piper) already say what, where and what to do
    for e in chain:  # a missing SDK first: nothing else can be right before it is installed
        if isinstance(e, ImportError):
            if "is required but not installed" in str(e):
                return _first_line(e)  # LeRobot's require_package: names the pip extra
            name = getattr(e, "name", None)
            return f"the Python package {name!r} it needs is not installed" if name else _first_line(e)
    for e in chain:
        code = getattr(e, "errno", None)
        if isinstance(e, PermissionError) or code == errno.EACCES:
            return (
                f"permission denied on {port} (add your user to the 'dialout' group and log in again, "
                f"or `sudo chmod 666 {port}`)"
            )
        if isinstance(e, FileNotFoundError) or code == errno.ENOENT:
            return f"{port} does not exist (is the robot plugged in and powered? `lerobot-find-port` lists the ports)"
        if code == errno.EBUSY:
            return f"{port} is busy (another program has it open)"
        if code in (errno.ENODEV, errno.ENXIO, errno.EIO):  # e.g. the USB adapter went away mid-run
            return f"{port} is not usable ({_first_line(e)}); is the robot plugged in and switched on?"
    for e in chain:
        text = str(e)
        missing = _MISSING_IDS.findall(text)
        if missing:
            return (
                f"motor(s) {', '.join(missing)} do not answer (check the power supply, the cable and the motor ids; "
                "`lerobot-setup-motors` sets them)"
            )
        if any(marker in text.lower() for marker in _NO_REPLY):
            return f"the motors do not answer ({_first_line(e)}); check the power supply and the cable"
    for e in chain:
        if isinstance(e, EOFError):  # LeRobot asked for a calibration on a terminal there is none of
            return (
                f"needs a calibration and there is no terminal to run it on: run `lerobot-calibrate "
                f"--robot.type={robot_type} ...` with the same --robot.id first"
            )
        if isinstance(e, DeviceNotConnectedError):
            return f"not connected ({_first_line(e)})"
    # Otherwise the most specific message: LeRobot's factory wrapper repeats the whole config.
    useful = [e for e in chain if not str(e).startswith("Error creating robot with config")]
    return _first_line(useful[0] if useful else chain[-1])
