"""Add a fourth scheduler in one file and compare it with EDF in the simulator.

    .venv/bin/python examples/custom_scheduler.py

"Least recently served" (LRS): serve the useful robots whose last chunk was generated from the
oldest observation relative to their current one, i.e. the most steps since their last service.

Registering happens when this module is imported. To ship the scheduler as a package of its own
(nothing in lerobot_armory edited), put the two classes below in a module of that package, say
``armory_lrs/__init__.py``, and declare it in the package's ``pyproject.toml`` under the
entry-point group ``lerobot_armory.schedulers``::

    [project.entry-points."lerobot_armory.schedulers"]
    lrs = "armory_lrs"

Once that package is installed (``pip install armory-lrs`` or ``pip install -e .``),
``--scheduler.type=lrs`` works in every lerobot-armory command: the scheduler registry imports
``armory_lrs`` the first time it is read. A plugin that fails to import is skipped with one
warning naming its entry point and the error; the other schedulers stay available.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.mirror import RobotMirror
from lerobot_armory.schedulers import Scheduler, SchedulerConfig, make_scheduler_config, useful
from lerobot_armory.sim.run import SimConfig, simulate, table


class LeastRecentlyServed(Scheduler):
    def select(self, robots: Sequence[RobotMirror], now: float) -> list[RobotMirror]:
        def steps_since_served(r: RobotMirror) -> int:
            assert r.obs_index is not None  # useful robots have an observation
            return r.obs_index - (r.last_served_index if r.last_served_index is not None else -10**9)

        return sorted(useful(robots), key=steps_since_served, reverse=True)[: self.max_batch_size]


@SchedulerConfig.register_subclass("lrs")
@dataclass
class LeastRecentlyServedConfig(SchedulerConfig):
    def build(self, profile: LatencyProfile, max_batch_size: int) -> Scheduler:
        return LeastRecentlyServed(profile, max_batch_size)


if __name__ == "__main__":
    runs = []
    for name in ("edf", "lrs"):
        cfg = SimConfig(preset="libero", mix="one-fast", robots=8, duration_s=60.0, scheduler=make_scheduler_config(name))
        runs.append(simulate(cfg.resolved(), seed=0))
    print(table(runs))
