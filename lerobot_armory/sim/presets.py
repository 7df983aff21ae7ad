"""Reference setups of docs/spec.md §5 as presets, and the fleet mixes.

A preset fixes the robots' timing (chunk size H, fps, h_min, fast/slow h_max), the default batch
cap, the default network and the default latency profile. A mix says which robots are fast.
"""

from __future__ import annotations

from dataclasses import dataclass

from lerobot_armory.errors import ConfigError
from lerobot_armory.robot_spec import RobotSpec

MIXES = ("all-fast", "one-fast", "half-fast")


@dataclass(frozen=True)
class Preset:
    """Timing of one reference setup.

    Attributes:
        name: preset name.
        chunk_size: H.
        fps: control frequency of every robot.
        h_min: minimum executed steps between two served observations.
        fast_h_max / slow_h_max: execution horizon of the fast / slow tier.
        batch_cap_homogeneous / batch_cap_heterogeneous: default ``b`` for all-fast fleets / mixed fleets.
        net_median_ms / net_sigma: default one-way network delay (log-normal median and shape).
        latency_profile: default ``d_infer`` profile name.
    """

    name: str
    chunk_size: int
    fps: float
    h_min: int
    fast_h_max: int
    slow_h_max: int
    batch_cap_homogeneous: int
    batch_cap_heterogeneous: int
    net_median_ms: float
    net_sigma: float
    latency_profile: str = "l40s-pi05"

    def default_batch_cap(self, mix: str) -> int:
        """docs/spec.md §5: ``b`` depends on whether the fleet is homogeneous."""
        return self.batch_cap_homogeneous if mix == "all-fast" else self.batch_cap_heterogeneous


# "libero": H=10, fps=20, h_min=1, h_max 6 (fast) / 10 (slow), b=3, server round trip 5-10 ms
# (one-way median 3.75 ms with a little jitter spans that range).
# "piper": 10 AgileX PiPER arms, H=20, fps=30, h_min=5, h_max 10 / 20, b=3 all-fast, 5 mixed.
PRESETS: dict[str, Preset] = {
    "libero": Preset("libero", 10, 20.0, 1, 6, 10, 3, 3, 3.75, 0.2),
    "piper": Preset("piper", 20, 30.0, 5, 10, 20, 3, 5, 3.75, 0.2),
}


def get_preset(name: str) -> Preset:
    """The preset called ``name`` (ConfigError naming the field if unknown)."""
    if name not in PRESETS:
        raise ConfigError("preset", f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
    return PRESETS[name]


def fast_count(mix: str, n_robots: int) -> int:
    """How many of ``n_robots`` are fast in ``mix`` (robots 0..k-1 are the fast ones)."""
    if mix not in MIXES:
        raise ConfigError("mix", f"unknown mix {mix!r}; known: {', '.join(MIXES)}")
    if n_robots < 1:
        raise ConfigError("robots", f"must be >= 1, got {n_robots}")
    if mix == "all-fast":
        return n_robots
    if mix == "one-fast":
        return 1
    return max(1, n_robots // 2)


def fleet_specs(preset: Preset, mix: str, n_robots: int, fast_weight: float = 1.0) -> list[RobotSpec]:
    """Robot specs of a fleet: the first robots are fast (weight ``fast_weight``), the rest slow."""
    if not fast_weight > 0:
        raise ConfigError("fast_weight", f"must be > 0, got {fast_weight}")
    n_fast = fast_count(mix, n_robots)
    specs = []
    for k in range(n_robots):
        fast = k < n_fast
        specs.append(
            RobotSpec(
                robot_id=f"robot{k:02d}",
                fps=preset.fps,
                chunk_size=preset.chunk_size,
                h_min=preset.h_min,
                h_max=preset.fast_h_max if fast else preset.slow_h_max,
                weight=fast_weight if fast else 1.0,
                tier="fast" if fast else "slow",
            )
        )
    return specs
