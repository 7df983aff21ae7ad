"""Helpers shared by the benchmark scripts: run a simulated config, check a target, report."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field

from lerobot_armory.schedulers import make_scheduler_config
from lerobot_armory.sim.run import SimConfig, simulate


def sim(scheduler: str, options: dict[str, object] | None = None, **kwargs: object) -> dict:
    """One simulated run (seed 0) of ``scheduler`` (with scheduler ``options``) and ``SimConfig`` overrides."""
    cfg = SimConfig(scheduler=make_scheduler_config(scheduler, **(options or {})), **kwargs).resolved()  # type: ignore[arg-type]
    return simulate(cfg, seed=0)


@dataclass
class Targets:
    """Collects (name, measured, limit) checks and exits non-zero if any is missed."""

    misses: list[str] = field(default_factory=list)

    def check(self, name: str, measured: float, limit: float, unit: str) -> None:
        ok = measured <= limit
        print(f"  {'PASS' if ok else 'MISS'}  {name}: {measured:.3f} {unit} (target <= {limit:g} {unit})")
        if not ok:
            self.misses.append(name)

    def check_min(self, name: str, measured: float, floor: float, unit: str = "") -> None:
        ok = measured >= floor
        print(f"  {'PASS' if ok else 'MISS'}  {name}: {measured:.3f} {unit} (target >= {floor:g} {unit})")
        if not ok:
            self.misses.append(name)

    def finish(self) -> None:
        if self.misses:
            print(f"{len(self.misses)} target(s) missed: {', '.join(self.misses)}")
            sys.exit(1)
        print("all targets met")
