"""The operator's grant rules (``--fleet.rules=FILE``): what each robot may be granted.

A robot *requests* a weight, a tier, an fps and horizons at registration; the operator decides
what it gets. The policy file (YAML or JSON) has a ``default`` rule and optional rules per robot
id and per named token (``@NAME TOKEN`` lines of ``--auth_token_file``)::

    default:                 # every robot without a more specific rule
      max_weight: 1          # requested weights are capped here (never raised)
      tiers: [fast, slow]    # a tier outside this list is granted the first one listed
      fps: [1, 60]           # an fps outside these bounds is refused
      h_min: [2, 50]         # requested h_min is raised/lowered into these bounds
      h_max: [1, 50]         # requested h_max above the bound is lowered; below it, refused
      max_device_share: 1.0  # fraction of device time the robot may use (1: no cap)
      min_horizon_s: 0.2     # shortest h_max / fps a robot may ask for (default: a batch of one)
    robots:
      arm-07: {max_weight: 3, tiers: [fast]}
    tokens:
      lab-b: {max_weight: 2, max_device_share: 0.25}

A robot rule beats a token rule, which beats ``default``; each gives only the fields it changes.
Without a file every robot gets the built-in default: weight at most 1, its own tier, fps and
horizons inside the physical bounds, no share cap, and a horizon (h_max / fps) at least as long
as a batch of one takes on this server: a robot whose chunk runs out before the next batch could
finish starves even alone, and a deadline scheduler would give it a slot in every batch. A
horizon above that can still cost the others under EDF when it is shorter than a full batch (in
a saturated simulated fleet, one robot with h_max 2 at 20 fps, 100 ms against 142 ms batches of
3, raised the others' starvation from 15.4 to 21.4 %, starving 68 % itself); set
``min_horizon_s`` to bound that. Registration answers with the grant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

from lerobot_armory.errors import ConfigError
from lerobot_armory.serving.config_files import read_config_file
from lerobot_armory.robot_spec import MAX_FPS, MAX_WEIGHT, MIN_FPS, TIERS
from lerobot_armory.serving.messages import Grant

FIELD = "fleet.rules"
_BIG = 1 << 30


@dataclass(frozen=True)
class Rule:
    """What one robot may be granted (see the module docstring for each field)."""

    max_weight: float = 1.0
    tiers: tuple[str, ...] = TIERS
    fps: tuple[float, float] = (MIN_FPS, MAX_FPS)
    h_min: tuple[int, int] = (0, _BIG)
    h_max: tuple[int, int] = (1, _BIG)
    max_device_share: float = 1.0
    min_horizon_s: float | None = None  # None: a batch of one's inference time (GrantRules.batch_s)

    def merged(self, where: str, entry: Any) -> Rule:
        """This rule with the fields ``entry`` (a mapping from the file) gives, checked."""
        if not isinstance(entry, dict):
            raise ConfigError(FIELD, f"{where}: expected a mapping of fields, got {type(entry).__name__}")
        known = {f.name for f in fields(Rule)}
        unknown = sorted(set(entry) - known)
        if unknown:
            raise ConfigError(FIELD, f"{where}: unknown field(s) {', '.join(map(str, unknown))} (known: {', '.join(sorted(known))})")
        changes: dict[str, Any] = {}
        if "max_weight" in entry:
            changes["max_weight"] = _number(where, "max_weight", entry["max_weight"], 0.0, MAX_WEIGHT, open_low=True)
        if "tiers" in entry:
            tiers = entry["tiers"]
            if not isinstance(tiers, list) or not tiers or any(t not in TIERS for t in tiers):
                raise ConfigError(FIELD, f"{where}: tiers must be a non-empty list of {', '.join(TIERS)}, got {tiers!r}")
            changes["tiers"] = tuple(tiers)
        if "fps" in entry:
            changes["fps"] = _bounds(where, "fps", entry["fps"], MIN_FPS, MAX_FPS, float)
        for name in ("h_min", "h_max"):
            if name in entry:
                changes[name] = _bounds(where, name, entry[name], 0 if name == "h_min" else 1, _BIG, int)
        if "min_horizon_s" in entry:
            changes["min_horizon_s"] = _number(where, "min_horizon_s", entry["min_horizon_s"], 0.0, 60.0)
        if "max_device_share" in entry:
            changes["max_device_share"] = _number(where, "max_device_share", entry["max_device_share"], 0.0, 1.0, open_low=True)
        return replace(self, **changes)


def _number(where: str, name: str, value: Any, low: float, high: float, open_low: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value > high or value < low or (open_low and value == low):
        lo = f"({low:g}" if open_low else f"[{low:g}"
        raise ConfigError(FIELD, f"{where}: {name} must be a number in {lo}, {high:g}], got {value!r}")
    return float(value)


def _bounds(where: str, name: str, value: Any, low: float, high: float, kind: type) -> tuple:
    if not (isinstance(value, list) and len(value) == 2):
        raise ConfigError(FIELD, f"{where}: {name} must be [low, high], got {value!r}")
    if kind is int and not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        raise ConfigError(FIELD, f"{where}: {name} bounds must be integers, got {value!r}")
    lo, hi = (_number(where, name, v, low, high) for v in value)
    if lo > hi:
        raise ConfigError(FIELD, f"{where}: {name} lower bound {lo:g} is above the upper bound {hi:g}")
    return (kind(lo), kind(hi))


@dataclass(frozen=True)
class GrantRequest:
    """What a robot asks for at registration."""

    robot_id: str
    fps: float
    h_min: int
    h_max: int
    weight: float
    tier: str


@dataclass
class GrantRules:
    """The default rule plus rules per robot id and per token name."""

    default: Rule
    robots: dict[str, Rule]
    tokens: dict[str, Rule]
    source: str = "built-in default"
    # A batch of one's inference time on this server (set by the server from its latency profile):
    # the shortest horizon a rule without min_horizon_s grants.
    batch_s: float = 0.0

    @classmethod
    def builtin(cls) -> GrantRules:
        return cls(Rule(), {}, {})

    @classmethod
    def load(cls, path: str) -> GrantRules:
        """Read a YAML (``.yaml``/``.yml``) or JSON policy file; every problem is one line."""
        data = read_config_file(path, FIELD)
        return cls.from_dict(data, path)

    @classmethod
    def from_dict(cls, data: Any, source: str = "<dict>") -> GrantRules:
        if not isinstance(data, dict):
            raise ConfigError(FIELD, f"{source}: expected a mapping with default / robots / tokens")
        unknown = sorted(set(data) - {"default", "robots", "tokens"})
        if unknown:
            raise ConfigError(FIELD, f"{source}: unknown section(s) {', '.join(map(str, unknown))} (known: default, robots, tokens)")
        default = Rule().merged(f"{source}: default", data.get("default") or {})
        sections: dict[str, dict[str, Rule]] = {}
        for section in ("robots", "tokens"):
            entries = data.get(section) or {}
            if not isinstance(entries, dict):
                raise ConfigError(FIELD, f"{source}: {section} must map names to rules")
            sections[section] = {str(k): default.merged(f"{source}: {section}.{k}", v) for k, v in entries.items()}
        return cls(default, sections["robots"], sections["tokens"], source)

    def describe(self) -> str:
        """One line for the start-up summary."""
        d = self.default
        share = f", device share <= {d.max_device_share:g}" if d.max_device_share < 1 else ""
        floor_s = self.batch_s if d.min_horizon_s is None else d.min_horizon_s
        horizon = f", horizon >= {1000 * floor_s:.0f} ms" if floor_s > 0 else ""
        return (
            f"{self.source}: weight <= {d.max_weight:g}, fps in [{d.fps[0]:g}, {d.fps[1]:g}]{share}{horizon} by default; "
            f"{len(self.robots)} robot rule(s), {len(self.tokens)} token rule(s)"
        )

    def rule_for(self, robot_id: str, token_name: str | None) -> tuple[Rule, str]:
        """The rule that applies and its name (``robot:ID``, ``token:NAME`` or ``default``)."""
        if robot_id in self.robots:
            return self.robots[robot_id], f"robot:{robot_id}"
        if token_name is not None and token_name in self.tokens:
            return self.tokens[token_name], f"token:{token_name}"
        return self.default, "default"

    def grant(self, request: GrantRequest, token_name: str | None = None, check_horizon: bool = True) -> tuple[Grant | None, list[str]]:
        """What ``request`` is granted, or None and every reason it is refused. ``check_horizon``
        False skips the horizon floor (openpi sessions: their fps and horizon are the operator's)."""
        rule, name = self.rule_for(request.robot_id, token_name)
        problems = []
        where = f"the grant rules ({name})"
        if not rule.fps[0] <= request.fps <= rule.fps[1]:
            problems.append(f"fps {request.fps:g} is outside {where}'s [{rule.fps[0]:g}, {rule.fps[1]:g}]")
        if request.h_max < rule.h_max[0]:
            problems.append(f"h_max {request.h_max} is below {where}'s minimum {rule.h_max[0]}")
        h_max = min(request.h_max, rule.h_max[1])
        floor_s = self.batch_s if rule.min_horizon_s is None else rule.min_horizon_s
        if check_horizon and floor_s > 0 and request.fps > 0 and h_max / request.fps < floor_s - 1e-9:
            why = "the inference time of a batch of one here" if rule.min_horizon_s is None else f"{where}'s min_horizon_s"
            need = math.ceil(floor_s * request.fps - 1e-9)
            problems.append(
                f"h_max {h_max} at {request.fps:g} fps is {1000 * h_max / request.fps:.0f} ms of actions, shorter than "
                f"{1000 * floor_s:.0f} ms ({why}): it would run dry before any chunk could reach it; "
                f"ask for h_max >= {need}" + (" (or the operator sets min_horizon_s in --fleet.rules)" if rule.min_horizon_s is None else "")
            )
        h_min = min(max(request.h_min, rule.h_min[0]), rule.h_min[1])
        if h_min > h_max:
            problems.append(f"h_min {h_min} (after {where}'s bounds) is above h_max {h_max}")
        if problems:
            return None, problems
        tier = request.tier if request.tier in rule.tiers else rule.tiers[0]
        weight = min(request.weight, rule.max_weight)
        return Grant(
            weight=weight, tier=tier, fps=request.fps, h_min=h_min, h_max=h_max, max_device_share=rule.max_device_share, rule=name
        ), []


def describe_grant(request: GrantRequest, grant: Grant) -> str:
    """One phrase of what the robot asked and got, naming only what differs (for logs)."""
    changed = [
        f"{name} {asked:g}->{got:g}" if isinstance(asked, float) else f"{name} {asked}->{got}"
        for name, asked, got in (
            ("weight", request.weight, grant.weight),
            ("tier", request.tier, grant.tier),
            ("h_min", request.h_min, grant.h_min),
            ("h_max", request.h_max, grant.h_max),
        )
        if asked != got
    ]
    share = f", device share <= {grant.max_device_share:g}" if grant.max_device_share < 1.0 else ""
    return f"granted by {grant.rule}" + (f" ({', '.join(changed)})" if changed else " as requested") + share
