"""Diagnostic: the small-fleet comparison at horizons the committed table did not pick.

``research/benchmarks/frontier.py`` scores schedulers against the committed exact optima, one horizon per
fleet (5 s where solvable, else the longest solved). A setting chosen on those 30 rows could be
fitted to them. This solves every small fleet again at other horizons (1, 1.5 and 2 s by default,
``--budget_s`` of exact search each; fleets not solved in time are listed as such) and prints
EDF, Lookahead, Rollout and Rollout ``tail=same`` as % of each optimum, told the episode's end as
in ``frontier.py``, with a count of rows under 95 % per scheduler.

No target (exits 0): the 95 % target is ``frontier.py``'s, on the committed rows. Some rows here
coincide with committed ones (the same fleet and horizon).

Run: ``.venv/bin/python research/benchmarks/frontier_horizons.py [--horizons=1,1.5,2] [--budget_s=20]
[--out=docs/results/frontier/other_horizons.md]`` (about 4 minutes on 2 cores with the defaults).
"""

from __future__ import annotations

import argparse
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _study import play_episode  # noqa: E402  (also puts research/ on sys.path)

from lerobot_armory.sim.presets import MIXES  # noqa: E402

from armory_research.optimal import episode_for, solve  # noqa: E402

# (label, scheduler, options): all told the episode's end.
COLUMNS = [
    ("EDF", "edf", {}),
    ("LA w=1", "lookahead", {}),
    ("rollout", "rollout", {}),
    ("rollout same", "rollout_same", {}),
]
SIZES = (3, 4, 5, 6)  # N = 2 is solved at 5 s everywhere
FLOOR = 95.0


def job(args: tuple[str, str, int, float, float]) -> tuple[tuple[str, str, int, float], bool, float, list[float]]:
    """Play every column on one episode, then solve it (the best of them as the incumbent)."""
    preset, mix, n, horizon, budget = args
    ep = episode_for(preset, mix, n, horizon)
    played = [play_episode(preset, ep, name, opts, tell_end=True) for _, name, opts in COLUMNS]
    best = max(played, key=lambda r: r.weighted_executed_s)
    res = solve(ep, best.weighted_executed_s, best.batches, time_limit_s=budget)
    return (preset, mix, n, horizon), res.exact, res.value, [r.weighted_executed_s for r in played]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--horizons", default="1,1.5,2", help="comma-separated horizons, seconds")
    ap.add_argument("--budget_s", type=float, default=20.0, help="exact search time per fleet and horizon")
    ap.add_argument("--out", help="also write the table to this markdown file")
    args = ap.parse_args()
    horizons = [float(h) for h in args.horizons.split(",")]
    jobs = [(p, m, n, h, args.budget_s) for h in horizons for p in ("libero", "piper") for m in MIXES for n in SIZES]
    head = "| preset | mix | N | horizon | optimum | " + " | ".join(c[0] for c in COLUMNS) + " |"
    md = [head, "|---" * (len(COLUMNS) + 5) + "|"]
    under: dict[str, list[float]] = {c[0]: [] for c in COLUMNS}
    solved = 0
    print(f"{len(jobs)} fleets x horizons, {args.budget_s:g} s of search each; % of the exact optimum, told the end")
    with ProcessPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        for (preset, mix, n, horizon), exact, optimum, values in pool.map(job, jobs):
            if not exact:
                print(f"    {preset:<7} {mix:<9} {n} {horizon:g} s: not solved in {args.budget_s:g} s")
                md.append(f"| {preset} | {mix} | {n} | {horizon:g} s | not solved | " + " | ".join("" for _ in COLUMNS) + " |")
                continue
            solved += 1
            fr = [100 * v / optimum for v in values]
            for (label, _, _), f in zip(COLUMNS, fr, strict=True):
                if f < FLOOR - 1e-9:
                    under[label].append(round(f, 1))
            cells = " ".join(f"{f:6.1f}%" for f in fr)
            print(f"    {preset:<7} {mix:<9} {n} {horizon:g} s: optimum {optimum:6.2f}  {cells}")
            md.append(f"| {preset} | {mix} | {n} | {horizon:g} s | {optimum:.2f} | " + " | ".join(f"{f:.1f}" for f in fr) + " |")
    summary = [f"\n{solved} of {len(jobs)} solved. Rows under {FLOOR:g} %:"]
    summary += [f"- {label}: {len(v)}" + (f" ({', '.join(map(str, sorted(v)))})" if v else "") for label, v in under.items()]
    print("\n".join(summary))
    if args.out:
        Path(args.out).write_text(
            "# Small fleets at other horizons, % of the exact optimum (told the episode's end)\n\n"
            f"`research/benchmarks/frontier_horizons.py --horizons={args.horizons} --budget_s={args.budget_s:g}`\n\n"
            + "\n".join(md)
            + "\n"
            + "\n".join(summary)
            + "\n"
        )
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
