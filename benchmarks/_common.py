"""Helpers shared by the benchmark scripts: run a simulated config, check a target, report."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field

from lerobot_armory.latency import load_profile
from lerobot_armory.schedulers import make_scheduler_config
from lerobot_armory.sim.optimal import Episode, EpisodeResult, play
from lerobot_armory.sim.presets import get_preset
from lerobot_armory.sim.run import SimConfig, simulate


def sim(scheduler: str, options: dict[str, object] | None = None, **kwargs: object) -> dict:
    """One simulated run (seed 0) of ``scheduler`` (with scheduler ``options``) and ``SimConfig`` overrides."""
    cfg = SimConfig(scheduler=make_scheduler_config(scheduler, **(options or {})), **kwargs).resolved()  # type: ignore[arg-type]
    return simulate(cfg, seed=0)


def play_episode(preset: str, ep: Episode, scheduler: str, options: dict[str, object], tell_end: bool) -> EpisodeResult:
    """``scheduler`` (with ``options``, the preset's latency profile) on a deterministic episode."""
    profile = load_profile(get_preset(preset).latency_profile)
    return play(ep, make_scheduler_config(scheduler, **options).build(profile, ep.max_batch_size), tell_end=tell_end)


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
