"""Fleet files: the robots a cluster must serve, what serves them, and the preset shorthand.

A fleet file (YAML ``.yaml``/``.yml`` or JSON) describes a fleet by groups of identical robots::

    latency_profile: l40s-pi05      # built-in profile name or a JSON profile file
    max_batch_size: 3
    scheduler: edf                  # rr | edf | lookahead, or {type: lookahead, depth: 2}; default edf
    network: {median_ms: 3.75, sigma: 0.2}   # one-way delay, log-normal (default: 3.75 ms, σ 0.2)
    max_robots_per_gpu: 64          # optional; default: no limit
    robots:
      - {count: 40, fps: 20, chunk_size: 10, h_min: 1, h_max: 6, weight: 3, tier: fast}
      - {count: 60, fps: 20, chunk_size: 10, h_min: 1, h_max: 10, tier: slow}

A fleet served by several policies on one device names them (each its profile and batch cap;
a missing one falls back to the top-level ``latency_profile`` / ``max_batch_size``) and each
group says which serves it (optional when there is one policy)::

    policies:
      pi05: {latency_profile: h100-pi05, max_batch_size: 5}
      act:  {latency_profile: act-h100.json, max_batch_size: 8}
    robots:
      - {count: 10, fps: 20, chunk_size: 10, h_min: 1, h_max: 6, policy: pi05}
      - {count: 10, fps: 20, chunk_size: 10, h_min: 1, h_max: 6, policy: act}

The simulator serves such a fleet on one device through a
:class:`~lerobot_armory.arbiter.PolicyArbiter`; a fleet with one named policy is the same fleet as
without ``policies:``. The capacity planner and the cluster simulation place such a fleet on GPUs
that each serve every policy, charging each robot its own policy's cost.

``weight`` defaults to 1 and ``tier`` to ``slow``; a group may carry a ``name`` (its robots are
called ``NAME-000``, ``NAME-001``...; default ``g<k>``). Every field is checked: an unknown key or
a bad value is one :class:`~lerobot_armory.errors.ConfigError` naming the field
(``robots[1].h_max: ...``), which the command lines print as one line and exit 2.

Instead of a file, ``preset:NAME:MIX:N[:FAST_WEIGHT]`` (e.g. ``preset:libero:half-fast:100``)
takes a reference preset's robots (docs/spec.md §5) with its default profile, batch cap and network, and
EDF.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field, replace
from collections.abc import Callable
from pathlib import Path
from typing import Any

from lerobot_armory.network_delay import LogNormalDelay
from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import LatencyProfile, load_profile
from lerobot_armory.robot_spec import TIERS, RobotSpec, spec_problems
from lerobot_armory.placement import Capacity, demand
from lerobot_armory.schedulers import EarliestDeadlineConfig, SchedulerConfig, make_scheduler_config
from lerobot_armory.sim.presets import MIXES, fleet_specs, get_preset

PRESET_PREFIX = "preset:"
DEFAULT_NET_MEDIAN_MS = 3.75
DEFAULT_NET_SIGMA = 0.2
# A fleet file describes a fleet, not a stress test of the parser: bound what it may ask for.
MAX_ROBOTS = 100_000

TOP_KEYS = ("latency_profile", "max_batch_size", "scheduler", "network", "max_robots_per_gpu", "policies", "robots")
GROUP_KEYS = ("count", "fps", "chunk_size", "h_min", "h_max", "weight", "tier", "name", "policy")
POLICY_KEYS = ("latency_profile", "max_batch_size")
NETWORK_KEYS = ("median_ms", "sigma")
_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_-]{0,63}")


@dataclass(frozen=True)
class RobotGroup:
    """``count`` identical robots.

    Attributes:
        name: prefix of the robots' ids.
        count: how many.
        fps / chunk_size / h_min / h_max / weight / tier: as :class:`~lerobot_armory.robot_spec.RobotSpec`.
    """

    name: str
    count: int
    fps: float
    chunk_size: int
    h_min: int
    h_max: int
    weight: float = 1.0
    tier: str = "slow"
    policy: str | None = None  # the policy serving the group (None: the fleet's only policy)

    def specs(self) -> list[RobotSpec]:
        """The group's robots, ids ``NAME-000``, ``NAME-001``, ..."""
        width = max(3, len(str(self.count - 1)))
        return [
            RobotSpec(
                f"{self.name}-{k:0{width}d}", self.fps, self.chunk_size, self.h_min, self.h_max, self.weight, self.tier
            )
            for k in range(self.count)
        ]


@dataclass(frozen=True)
class PolicySpec:
    """One policy of a mixed fleet: the model its robots' batches run on the shared device.

    Attributes:
        name: the name groups refer to (``policy: NAME``).
        latency_profile: built-in profile name or JSON profile file: its ``d_infer(b)``.
        max_batch_size: its batch cap.
    """

    name: str
    latency_profile: str
    max_batch_size: int

    def profile(self) -> LatencyProfile:
        """The policy's latency profile."""
        return load_profile(self.latency_profile)


@dataclass
class Fleet:
    """A fleet and what serves it: one latency profile and batch cap per GPU, one scheduler, one network.

    Attributes:
        groups: the robots, by group.
        latency_profile: built-in profile name or JSON profile file (every GPU runs it).
        max_batch_size: batch cap b of every GPU.
        scheduler: the scheduler every GPU runs (each GPU builds its own).
        net_median_ms / net_sigma: one-way network delay, log-normal, uplink and downlink alike.
        max_robots_per_gpu: robots one GPU accepts at most (None: no limit).
        source: the file or shorthand it came from (for messages).
        policies: the policies sharing each device when there are several (each group names
            one); empty for the ordinary one-policy fleet, whose profile and cap are the fleet's.
    """

    groups: tuple[RobotGroup, ...]
    latency_profile: str
    max_batch_size: int
    scheduler: SchedulerConfig = field(default_factory=EarliestDeadlineConfig)
    net_median_ms: float = DEFAULT_NET_MEDIAN_MS
    net_sigma: float = DEFAULT_NET_SIGMA
    max_robots_per_gpu: int | None = None
    source: str = "<fleet>"
    policies: tuple[PolicySpec, ...] = ()

    @property
    def robots(self) -> int:
        return sum(g.count for g in self.groups)

    @property
    def is_mixed(self) -> bool:
        """Whether several policies share the device (the arbiter's case)."""
        return len(self.policies) > 1

    def policy_of(self) -> dict[str, str]:
        """Robot id -> policy name, for a mixed fleet (every group names its policy)."""
        return {s.robot_id: g.policy for g in self.groups for s in g.specs() if g.policy is not None}

    def policy_counts(self) -> dict[str, int]:
        """Robots per policy, in the policies' order (a policy no group uses counts 0)."""
        counts = {p.name: 0 for p in self.policies}
        for g in self.groups:
            if g.policy is not None:
                counts[g.policy] += g.count
        return counts

    def only(self, policy: str) -> Fleet:
        """The robots of ``policy`` alone, as a one-policy fleet on GPUs of their own (its profile
        and cap, the same scheduler and network)."""
        p = next((p for p in self.policies if p.name == policy), None)
        if p is None:
            raise ConfigError("policies", f"{self.source} has no policy {policy!r}")
        groups = tuple(replace(g, policy=None) for g in self.groups if g.policy == policy)
        return Fleet(groups, p.latency_profile, p.max_batch_size, self.scheduler, self.net_median_ms, self.net_sigma,
                     self.max_robots_per_gpu, f"{self.source}[{policy}]")  # fmt: skip

    def specs(self) -> list[RobotSpec]:
        """Every robot, group by group (the join order is shuffled by the cluster simulation)."""
        return [s for g in self.groups for s in g.specs()]

    def profile(self, name: str | None = None) -> LatencyProfile:
        """The fleet's latency profile (or ``name``, for a GPU of another kind)."""
        return load_profile(name or self.latency_profile)

    def network(self) -> LogNormalDelay:
        return LogNormalDelay(self.net_median_ms / 1000.0, self.net_sigma)

    def capacity(self, profile: str | None = None) -> Capacity:
        """One GPU's :class:`~lerobot_armory.placement.Capacity` at the fleet's batch cap and network median."""
        return Capacity(tuple(self.profile(profile).table_s(self.max_batch_size)), self.net_median_ms / 1000.0)

    def policy_capacities(self) -> dict[str, Capacity]:
        """Each policy's capacity on the shared device (its profile at its cap), for a mixed fleet."""
        one_way = self.net_median_ms / 1000.0
        return {p.name: Capacity(tuple(p.profile().table_s(p.max_batch_size)), one_way) for p in self.policies}

    def capacity_of(self) -> Callable[[RobotSpec], Capacity] | None:
        """For a mixed fleet, robot -> its policy's capacity (what placement charges each robot);
        None for a one-policy fleet (every robot costs the GPU's capacity)."""
        if not self.is_mixed:
            return None
        return _PolicyCapacity(self.policy_capacities(), self.policy_of())

    def group_demand(self, group: RobotGroup, profile: str | None = None) -> float:
        """Predicted device seconds per second one robot of ``group`` needs (its policy's capacity when mixed)."""
        if self.is_mixed:
            assert group.policy is not None  # every group of a mixed fleet names its policy (checked at load)
            return demand(group.specs()[0], self.policy_capacities()[group.policy])
        return demand(group.specs()[0], self.capacity(profile))

    def total_demand(self, profile: str | None = None) -> float:
        """Predicted GPUs' worth of device time the whole fleet needs (the placement load model)."""
        return sum(g.count * self.group_demand(g, profile) for g in self.groups if g.count)

    def tier_counts(self) -> dict[str, int]:
        counts = dict.fromkeys(TIERS, 0)
        for g in self.groups:
            counts[g.tier] += g.count
        return counts

    def describe(self) -> str:
        """One line: size, tiers, profile, cap, scheduler, network."""
        tiers = ", ".join(f"{n} {t}" for t, n in self.tier_counts().items() if n)
        if self.is_mixed:
            counts = self.policy_counts()
            served = "; ".join(
                f"{p.name}: {counts[p.name]} robots on {p.latency_profile}, b={p.max_batch_size}" for p in self.policies
            )
            return (
                f"{self.source}: {self.robots} robots ({tiers}); {served}; {self.scheduler.label()}, "
                f"network {self.net_median_ms:g} ms / σ {self.net_sigma:g}"
            )
        return (
            f"{self.source}: {self.robots} robots ({tiers}); {self.latency_profile}, b={self.max_batch_size}, "
            f"{self.scheduler.label()}, network {self.net_median_ms:g} ms / σ {self.net_sigma:g}"
        )


def load_fleet(arg: str) -> Fleet:
    """A fleet from a file path or the ``preset:NAME:MIX:N[:FAST_WEIGHT]`` shorthand (ConfigError if bad)."""
    if not arg:
        raise ConfigError(
            "fleet", "give a fleet file (YAML or JSON) or preset:NAME:MIX:N, e.g. preset:libero:half-fast:100"
        )
    if arg.startswith(PRESET_PREFIX):
        return preset_fleet(arg)
    path = Path(arg)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("fleet", f"cannot read {arg}: {exc}") from None
    yaml = None
    if path.suffix in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise ConfigError(
                "fleet", f"{arg}: reading YAML needs PyYAML (pip install pyyaml); or write the file as JSON"
            ) from None
    try:
        data = yaml.safe_load(text) if yaml is not None else json.loads(text)
    except Exception as exc:  # yaml.YAMLError / json.JSONDecodeError: one line either way
        first = (str(exc).strip().splitlines() or [""])[0]
        raise ConfigError("fleet", f"{arg} does not parse: {first}") from None
    return fleet_from_dict(data, arg)


def preset_fleet(arg: str) -> Fleet:
    """``preset:NAME:MIX:N[:FAST_WEIGHT]``: a reference preset's fleet, its defaults, EDF."""
    parts = arg[len(PRESET_PREFIX) :].split(":")
    usage = f"expected preset:NAME:MIX:N[:FAST_WEIGHT] (e.g. preset:libero:half-fast:100), got {arg!r}"
    if len(parts) not in (3, 4):
        raise ConfigError("fleet", usage)
    name, mix, n_text = parts[:3]
    preset = get_preset(name)
    if mix not in MIXES:
        raise ConfigError("fleet", f"unknown mix {mix!r} in {arg!r}; known: {', '.join(MIXES)}")
    try:
        n = int(n_text)
        fast_weight = float(parts[3]) if len(parts) == 4 else 1.0
    except ValueError:
        raise ConfigError("fleet", usage) from None
    if not 1 <= n <= MAX_ROBOTS:
        raise ConfigError("fleet", f"robot count must be in [1, {MAX_ROBOTS}], got {n}")
    specs = fleet_specs(preset, mix, n, fast_weight)
    groups = []
    for tier in TIERS:
        rows = [s for s in specs if s.tier == tier]
        if rows:
            s = rows[0]
            groups.append(RobotGroup(tier, len(rows), s.fps, s.chunk_size, s.h_min, s.h_max, s.weight, tier))
    return Fleet(
        tuple(groups), preset.latency_profile, preset.default_batch_cap(mix), EarliestDeadlineConfig(),
        preset.net_median_ms, preset.net_sigma, None, arg,
    )  # fmt: skip


def fleet_from_dict(data: Any, source: str = "<dict>") -> Fleet:
    """Check a parsed fleet file field by field; the first problem is a ConfigError naming its field."""

    def err(field_name: str, message: str) -> ConfigError:
        return ConfigError(field_name, f"{message} (in {source})")

    if not isinstance(data, dict):
        raise err("fleet", f"expected a mapping with {', '.join(TOP_KEYS)}, got {type(data).__name__}")
    _no_unknown(data, TOP_KEYS, "", err)
    policies = _policies(data, source, err)
    if policies:
        # the fleet-level profile and cap are the first policy's: one-policy code reads them
        profile_name, cap = policies[0].latency_profile, policies[0].max_batch_size
        raw_scheduler = data.get("scheduler", "edf")
        scheduler = _scheduler(raw_scheduler, policies[0].profile(), cap, err)
        for p in policies[1:]:  # the one scheduler type is built for every policy: check each
            _scheduler(raw_scheduler, p.profile(), p.max_batch_size, err)
    else:
        if "latency_profile" not in data:
            raise err("latency_profile", "missing (a built-in profile name or a JSON profile file)")
        profile_name, profile = _profile(data["latency_profile"], "latency_profile", source, err)
        cap = _cap(data.get("max_batch_size"), "max_batch_size", err)
        scheduler = _scheduler(data.get("scheduler", "edf"), profile, cap, err)
    network = data.get("network", {})
    if not isinstance(network, dict):
        raise err("network", f"must be a mapping with {', '.join(NETWORK_KEYS)}, got {network!r}")
    _no_unknown(network, NETWORK_KEYS, "network.", err)
    median = network.get("median_ms", DEFAULT_NET_MEDIAN_MS)
    sigma = network.get("sigma", DEFAULT_NET_SIGMA)
    if not (_is_real(median) and math.isfinite(median) and 0 <= median <= 10_000):
        raise err("network.median_ms", f"must be a number of ms in [0, 10000], got {median!r}")
    if not (_is_real(sigma) and math.isfinite(sigma) and 0 <= sigma <= 10):
        raise err("network.sigma", f"must be a number in [0, 10], got {sigma!r}")
    per_gpu = data.get("max_robots_per_gpu")
    if per_gpu is not None and not (_is_int(per_gpu) and per_gpu >= 1):
        raise err("max_robots_per_gpu", f"must be an integer >= 1, got {per_gpu!r}")
    groups = _groups(data.get("robots"), err, [p.name for p in policies])
    # One named policy is the ordinary fleet: same profile, cap, robots and results.
    mixed = tuple(policies) if len(policies) > 1 else ()
    if not mixed:
        groups = [replace(g, policy=None) for g in groups]
    return Fleet(tuple(groups), profile_name, cap, scheduler, float(median), float(sigma), per_gpu, source, mixed)


def _profile(raw: Any, field_name: str, source: str, err) -> tuple[str, LatencyProfile]:
    """A profile name or file (a relative file is looked for beside the fleet file), loaded."""
    if not isinstance(raw, str) or not raw:
        raise err(field_name, f"must be a profile name or file, got {raw!r}")
    name = raw
    if not (Path(name).is_absolute() or name in _builtin_names()) and (Path(source).parent / name).is_file():
        name = str(Path(source).parent / name)  # a profile file beside the fleet file
    try:
        return name, load_profile(name)
    except ConfigError as exc:
        raise err(field_name, exc.message) from None


def _cap(raw: Any, field_name: str, err) -> int:
    if not (_is_int(raw) and 1 <= raw <= 1024):
        raise err(field_name, f"must be an integer in [1, 1024], got {raw!r}")
    return raw


def _policies(data: dict, source: str, err) -> list[PolicySpec]:
    """The ``policies:`` mapping (empty without one); an entry's missing profile or cap falls
    back to the top-level one, and a policy with neither is an error naming its field."""
    raw = data.get("policies")
    if raw is None:
        return []
    if not isinstance(raw, dict) or not raw:
        raise err("policies", f"must be a non-empty mapping of name -> {{{', '.join(POLICY_KEYS)}}}, got {raw!r}")
    policies = []
    for name, entry in raw.items():
        where = f"policies.{name}"
        if not (isinstance(name, str) and _NAME.fullmatch(name)):
            raise err("policies", f"a policy name must be a short identifier (letters, digits, - and _), got {name!r}")
        if entry is None:
            entry = {}
        if not isinstance(entry, dict):
            raise err(where, f"must be a mapping of {', '.join(POLICY_KEYS)}, got {entry!r}")
        _no_unknown(entry, POLICY_KEYS, f"{where}.", err)
        merged = {k: entry.get(k, data.get(k)) for k in POLICY_KEYS}
        if merged["latency_profile"] is None:
            raise err(f"{where}.latency_profile", "missing (a built-in profile name or a JSON profile file)")
        if merged["max_batch_size"] is None:
            raise err(f"{where}.max_batch_size", "missing (an integer in [1, 1024])")
        field_of = {k: f"{where}.{k}" if k in entry else k for k in POLICY_KEYS}
        profile_name, _ = _profile(merged["latency_profile"], field_of["latency_profile"], source, err)
        cap = _cap(merged["max_batch_size"], field_of["max_batch_size"], err)
        policies.append(PolicySpec(name, profile_name, cap))
    return policies


def _groups(raw: Any, err, policies: list[str] | None = None) -> list[RobotGroup]:
    if not isinstance(raw, list) or not raw:
        raise err("robots", "must be a non-empty list of robot groups ({count, fps, chunk_size, h_min, h_max, ...})")
    groups, names, total = [], set(), 0
    for k, entry in enumerate(raw):
        where = f"robots[{k}]"
        if not isinstance(entry, dict):
            raise err(where, f"must be a mapping of {', '.join(GROUP_KEYS)}, got {entry!r}")
        _no_unknown(entry, GROUP_KEYS, f"{where}.", err)
        for key in ("count", "fps", "chunk_size", "h_min", "h_max"):
            if key not in entry:
                raise err(f"{where}.{key}", "missing")
        count = entry["count"]
        if not (_is_int(count) and 1 <= count <= MAX_ROBOTS):
            raise err(f"{where}.count", f"must be an integer in [1, {MAX_ROBOTS}], got {count!r}")
        total += count
        if total > MAX_ROBOTS:
            raise err("robots", f"more than {MAX_ROBOTS} robots in all")
        name = entry.get("name", f"g{k}")
        if not (isinstance(name, str) and _NAME.fullmatch(name)):
            raise err(f"{where}.name", f"must be a short identifier (letters, digits, - and _), got {name!r}")
        if name in names:
            raise err(f"{where}.name", f"{name!r} names two groups")
        names.add(name)
        policy = _group_policy(entry, where, policies or [], err)
        weight, tier = entry.get("weight", 1.0), entry.get("tier", "slow")
        problems = spec_problems(
            f"{name}-0", entry["fps"], entry["chunk_size"], entry["h_min"], entry["h_max"], weight, tier
        )
        if problems:  # the mirror's own validator: the fleet file and a live registration agree
            field_name, _, why = problems[0].partition(": ")
            raise err(f"{where}.{field_name}", why)
        groups.append(
            RobotGroup(
                name,
                count,
                float(entry["fps"]),
                entry["chunk_size"],
                entry["h_min"],
                entry["h_max"],
                float(weight),
                tier,
                policy,
            )
        )
    return groups


def _group_policy(entry: dict, where: str, policies: list[str], err) -> str | None:
    """The group's ``policy``: required when the fleet names several, must be one of them."""
    if "policy" not in entry:
        if len(policies) > 1:
            raise err(f"{where}.policy", f"missing (the fleet names several policies: {', '.join(policies)})")
        return policies[0] if policies else None
    name = entry["policy"]
    if not policies:
        raise err(f"{where}.policy", f"names policy {name!r} but the fleet has no policies: mapping")
    if name not in policies:
        raise err(f"{where}.policy", f"unknown policy {name!r} (the fleet's policies: {', '.join(policies)})")
    return name


def _scheduler(raw: Any, profile: LatencyProfile, cap: int, err) -> SchedulerConfig:
    if isinstance(raw, str):
        name, knobs = raw, {}
    elif isinstance(raw, dict) and isinstance(raw.get("type"), str):
        name, knobs = raw["type"], {k: v for k, v in raw.items() if k != "type"}
    else:
        raise err(
            "scheduler", f"must be a scheduler name (rr, edf, lookahead) or {{type: NAME, knob: value}}, got {raw!r}"
        )
    try:
        cfg = make_scheduler_config(name, **knobs)
    except ConfigError as exc:
        raise err("scheduler", exc.message) from None
    except TypeError:
        known = [f for f in getattr(make_scheduler_config(name), "__dataclass_fields__", {})]
        raise err(
            "scheduler", f"unknown knob(s) {', '.join(sorted(knobs))} for {name} (known: {', '.join(known) or 'none'})"
        ) from None
    try:
        cfg.make(profile, cap)  # the scheduler's own checks of its knobs
    except ConfigError as exc:
        name = exc.field if exc.field.startswith("scheduler") else f"scheduler.{exc.field}"
        raise err(name, exc.message) from None
    except (TypeError, ValueError) as exc:
        raise err("scheduler", str(exc).splitlines()[0] if str(exc) else type(exc).__name__) from None
    return cfg


def _no_unknown(mapping: dict, known: tuple[str, ...], prefix: str, err) -> None:
    unknown = sorted(str(k) for k in mapping if k not in known)
    if unknown:
        raise err(f"{prefix}{unknown[0]}", f"unknown key (known: {', '.join(known)})")


def _builtin_names() -> set[str]:
    from lerobot_armory.inference_latency import BUILTIN_PROFILES

    return set(BUILTIN_PROFILES)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_real(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def with_overrides(fleet: Fleet, latency_profile: str | None = None, max_batch_size: int | None = None) -> Fleet:
    """The fleet on another GPU kind or batch cap (command-line overrides), checked."""
    changes: dict[str, Any] = {}
    if fleet.is_mixed and (latency_profile or max_batch_size is not None):
        raise ConfigError(
            "latency_profile" if latency_profile else "max_batch_size",
            f"{fleet.source} names several policies: set each one's profile and cap in its policies: entry",
        )
    if latency_profile:
        load_profile(latency_profile)
        changes["latency_profile"] = latency_profile
    if max_batch_size is not None:
        if max_batch_size < 1:
            raise ConfigError("max_batch_size", f"must be >= 1, got {max_batch_size}")
        changes["max_batch_size"] = max_batch_size
    return replace(fleet, **changes) if changes else fleet


@dataclass(frozen=True, eq=False)
class _PolicyCapacity:
    """Robot -> its policy's :class:`Capacity`, hashable by identity (placement memoizes on it).

    Robots are looked up by id: the cluster simulation renames robots (``r0000``...) only after
    placing them, so ids here are the fleet's own.
    """

    capacities: dict[str, Capacity]
    policy_of: dict[str, str]

    def __call__(self, spec: RobotSpec) -> Capacity:
        return self.capacities[self.policy_of[spec.robot_id]]
