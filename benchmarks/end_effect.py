"""Diagnostic: how much of Rollout's gap to the offline optimum is the end of the episode?

The optimum of ``lerobot_armory.sim.optimal`` knows that nothing after the horizon counts, so
near the end it picks batches for the last few ticks only. An online scheduler cannot: a live
fleet has no end, and Rollout scores a 1 s window that runs past it. On the short cold-start
horizons that the exact search can solve for the loaded fleets (1-1.5 s), that end is a large
part of the episode.

This replays the committed optimum rows (``docs/results/frontier/optimum_search.json``, the
exact ones) with Rollout as registered and with Rollout told the episode's end
(``play(tell_end=True)`` sets ``Scheduler.episode_end_s``: its window is clipped there; live it
is inf, a fleet has no end), and prints both as % of the optimum. No target: it only tells a reader what the
misses of ``benchmarks/frontier.py`` are made of, so it always exits 0.

Run: ``.venv/bin/python benchmarks/end_effect.py`` (a few seconds).
"""

from __future__ import annotations

import json
from pathlib import Path

from lerobot_armory.latency import load_profile
from lerobot_armory.schedulers import make_scheduler_config
from lerobot_armory.sim.optimal import episode_for, play
from lerobot_armory.sim.presets import MIXES, get_preset

ROWS = Path(__file__).resolve().parents[1] / "docs" / "results" / "frontier" / "optimum_search.json"
FLOOR = 95.0


def main() -> None:
    rows = [r for r in json.loads(ROWS.read_text()) if r["exact"]]
    rows.sort(key=lambda r: (r["preset"], MIXES.index(r["mix"]), r["robots"]))
    print("Rollout (w=1) as % of the exact optimum: as registered / told the episode's end")
    print(f"    {'preset':<7} {'mix':<9} {'N':>2} {'horizon':>7}  {'rollout':>8} {'end known':>9}")
    misses = [0, 0]
    for r in rows:
        ep = episode_for(r["preset"], r["mix"], r["robots"], r["horizon_s"])
        profile = load_profile(get_preset(r["preset"]).latency_profile)
        out = []
        for tell in (False, True):
            sched = make_scheduler_config("rollout").build(profile, ep.max_batch_size)
            out.append(100 * play(ep, sched, tell_end=tell).weighted_executed_s / r["optimum"])
        for i, x in enumerate(out):
            misses[i] += x < FLOOR
        flag = "  (under 95 % as registered)" if out[0] < FLOOR else ""
        print(f"    {r['preset']:<7} {r['mix']:<9} {r['robots']:>2} {r['horizon_s']:>5g} s  {out[0]:>7.1f}% {out[1]:>8.1f}%{flag}")
    print(f"\nrows under {FLOOR:g} %: {misses[0]} as registered, {misses[1]} with the end known (of {len(rows)})")


if __name__ == "__main__":
    main()
