"""Network delay model: each one-way delay is log-normal, ``ln d ~ N(ln m, σ²)`` (docs/spec.md §5).

One model, two users: the simulator draws its network from it and the robot side's network
emulator (:mod:`lerobot_armory.robot.netem`) delays real messages with it, so live and simulated
runs see the same network. It lives at the top of the package, beside neither, so the robot side
does not have to import the simulator (and with it every scheduler) to emulate a network.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lerobot_armory.errors import ConfigError


@dataclass(frozen=True)
class LogNormalDelay:
    """One-way delay with median ``median_s`` and shape ``sigma`` (σ = 0 gives exactly the median).

    Delays are drawn independently per request from the generator passed in, so a run is
    reproducible from its seed.
    """

    median_s: float
    sigma: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.median_s) and self.median_s >= 0):
            raise ConfigError("net_median_ms", f"must be >= 0, got {self.median_s * 1000}")
        if not (math.isfinite(self.sigma) and self.sigma >= 0):
            raise ConfigError("net_sigma", f"must be >= 0, got {self.sigma}")

    def sample(self, rng: np.random.Generator, size: int | None = None) -> np.ndarray | float:
        """``size`` delays in seconds (one float when ``size`` is None)."""
        if self.sigma == 0 or self.median_s == 0:
            return self.median_s if size is None else np.full(size, self.median_s)
        return rng.lognormal(math.log(self.median_s), self.sigma, size)

    @property
    def mean_s(self) -> float:
        """Expected delay (log-normal mean)."""
        return self.median_s * math.exp(self.sigma**2 / 2)
