"""What a robot declares when it joins (:class:`RobotSpec`) and the bounds every declaration is
checked against, whichever way it arrives (gRPC, openpi, a fleet file, the simulator)."""

from __future__ import annotations

import numbers
from dataclasses import dataclass

from lerobot_armory.errors import ConfigError

TIERS = ("fast", "slow")
# Longest robot id: ids travel in every log line, metric label and status row.
MAX_ROBOT_ID = 128

# Physical bounds of a robot's declared rates: beyond them no controller exists and the tick
# arithmetic (1 / fps, ticks * fps) leaves the floats (fps = 1e308 made ``math.ceil`` raise).
MIN_FPS = 0.01
MAX_FPS = 1000.0
MAX_WEIGHT = 1e6


@dataclass(frozen=True)
class RobotSpec:
    """What a robot declares when it joins: its control rate, horizon and importance.

    Attributes:
        robot_id: unique name of the robot in the fleet.
        fps: control frequency f_c (robot steps per second).
        chunk_size: H, actions per predicted chunk.
        h_min: the server does not serve the robot again before it executed this many steps
            since the observation of its last served request.
        h_max: the robot executes at most this many actions of a chunk.
        weight: w_j, value of one executed second of this robot (Lookahead's objective).
        tier: reporting label, ``fast`` (dynamic task, short h_max) or ``slow``.

    Raises:
        ConfigError: naming every problem :func:`spec_problems` finds (``field`` is the first's).
    """

    robot_id: str
    fps: float
    chunk_size: int
    h_min: int
    h_max: int
    weight: float = 1.0
    tier: str = "slow"

    def __post_init__(self) -> None:
        problems = spec_problems(self.robot_id, self.fps, self.chunk_size, self.h_min, self.h_max, self.weight, self.tier)
        if problems:
            raise ConfigError.listing(problems)


def _shown(value: object, limit: int = 40) -> str:
    """``repr(value)``, cut short: values may come from the wire, and an error echoes them."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _is_real(value: object) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_int(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def spec_problems(
    robot_id: str, fps: float, chunk_size: int | None, h_min: int, h_max: int, weight: float, tier: str
) -> list[str]:
    """Every problem of a robot's declared spec, as ``field: why`` strings (empty: valid).

    The one validator of what a robot declares: :class:`RobotSpec` raises with it, the server
    answers a registration with it and the client command line checks its flags with it, so the
    three agree, and each names every problem at once rather than the first.

    Values may come straight from the wire or a command line, so a value of the wrong type (a
    string fps, a float horizon) is a problem, never an exception. ``chunk_size`` None means not known yet (a robot learns the
    policy's H only when it registers): the checks that need it are left to the server.
    A relation (``h_min <= h_max <= H``) is checked only when its fields are valid on their own,
    so one bad value is named once.
    """
    problems = []
    if not (isinstance(robot_id, str) and 0 < len(robot_id) <= MAX_ROBOT_ID and robot_id.isprintable()):
        problems.append(f"robot_id: must be a non-empty string of at most {MAX_ROBOT_ID} printable characters")
    if not (_is_real(fps) and MIN_FPS <= fps <= MAX_FPS):  # NaN fails the comparison
        problems.append(f"fps: must be a number of steps per second in [{MIN_FPS:g}, {MAX_FPS:g}], got {_shown(fps)}")
    chunk_ok = chunk_size is None or (_is_int(chunk_size) and chunk_size >= 1)
    if not chunk_ok:
        problems.append(f"chunk_size: must be an integer >= 1, got {_shown(chunk_size)}")
    h_min_ok = _is_int(h_min) and h_min >= 0
    if not h_min_ok:
        problems.append(f"h_min: must be an integer >= 0, got {_shown(h_min)}")
    h_max_ok = _is_int(h_max) and h_max >= 1
    if not h_max_ok:
        problems.append(f"h_max: must be an integer >= 1, got {_shown(h_max)}")
    if h_min_ok and h_max_ok and h_min > h_max:
        problems.append(f"h_min: h_min={h_min} is larger than h_max={h_max}")
    if h_max_ok and chunk_ok and chunk_size is not None and h_max > chunk_size:
        problems.append(f"h_max: h_max={h_max} is larger than the chunk size H={chunk_size}")
    if not (_is_real(weight) and 0 < weight <= MAX_WEIGHT):
        problems.append(f"weight: must be a positive number up to {MAX_WEIGHT:g}, got {_shown(weight)}")
    if not (isinstance(tier, str) and tier in TIERS):
        problems.append(f"tier: must be one of {', '.join(TIERS)}, got {_shown(tier)}")
    return problems
