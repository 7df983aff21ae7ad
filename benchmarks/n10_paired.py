"""N = 10 per-tier starvation against EDF with paired seeds and 95 % confidence intervals.

``benchmarks/frontier.py`` and ``lerobot-armory-frontier`` compare tier means over a few seeds,
where a difference of a few tenths of a point can be noise. Here every setting runs on the same
seeds as EDF (same network draws), and each difference is reported as the mean of the per-seed
differences ± 1.96 standard errors, so a reader can tell a win from a tie.

Settings: Rollout as registered (EDF order in its rollouts) and Rollout with ``order=gain,
tail=same`` (its rollouts serve the largest weighted coverage gain first, in full batches), each
at several fast-robot weights. Fleets: libero and piper, one-fast and half-fast, N = 10.

Target (exits 1 on a miss), the issue's: for every fleet some setting and weight is at least as
good as EDF on both tiers' mean starvation and strictly better on the fast tier. The table also
marks a win whose confidence intervals exclude a loss on both tiers (``significant``).

Run: ``.venv/bin/python benchmarks/n10_paired.py [--seeds=48] [--duration_s=120] [--out=FILE.md]``
(about 15 minutes on 2 cores with the defaults).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import Targets  # noqa: E402

from lerobot_armory.schedulers import make_scheduler_config  # noqa: E402
from lerobot_armory.sim.run import SimConfig, simulate  # noqa: E402

FLEETS = [("libero", "one-fast"), ("libero", "half-fast"), ("piper", "one-fast"), ("piper", "half-fast")]
# (label, scheduler options, fast-robot weights)
SETTINGS: list[tuple[str, dict[str, str], tuple[float, ...]]] = [
    ("rollout", {}, (1.75, 2.0, 2.1, 2.25, 2.5, 3.0)),
    ("rollout gain", {"order": "gain", "tail": "same"}, (2.0, 2.25, 2.3, 3.0, 3.5, 3.75, 5.0, 5.25)),
]


def run_one(job: tuple[str, str, str, dict[str, str], float, int, float]) -> tuple[float, float]:
    """(fast %, slow %) starvation of one seed."""
    preset, mix, name, options, weight, seed, duration = job
    cfg = SimConfig(
        preset=preset, mix=mix, robots=10, scheduler=make_scheduler_config(name, **options),
        fast_weight=weight, duration_s=duration,
    ).resolved()  # fmt: skip
    tiers = simulate(cfg, seed)["tiers"]
    return tiers["fast"]["starvation_pct"], tiers["slow"]["starvation_pct"]


def interval(diffs: np.ndarray) -> tuple[float, float]:
    """Mean and 95 % half-width (normal approximation) of per-seed differences."""
    half = 1.96 * diffs.std(ddof=1) / math.sqrt(len(diffs)) if len(diffs) > 1 else float("nan")
    return float(diffs.mean()), half


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    # 48 seeds: at 12, wins of a few tenths of a point (libero) are inside the intervals.
    ap.add_argument("--seeds", type=int, default=48)
    ap.add_argument("--duration_s", type=float, default=120.0)
    ap.add_argument("--out", help="also write the tables to this markdown file")
    args = ap.parse_args()

    who = [("EDF", "edf", {}, 1.0)]
    who += [(label, "rollout", opts, w) for label, opts, weights in SETTINGS for w in weights]
    jobs = [
        (preset, mix, name, opts, w, seed, args.duration_s)
        for preset, mix in FLEETS
        for _, name, opts, w in who
        for seed in range(args.seeds)
    ]
    print(f"{len(jobs)} simulated runs ({args.seeds} seeds x {args.duration_s:g} s each)...", file=sys.stderr)
    with ProcessPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        results = iter(pool.map(run_one, jobs, chunksize=4))
        runs = {
            (preset, mix, label, w): np.array([next(results) for _ in range(args.seeds)])
            for preset, mix in FLEETS
            for label, _, _, w in who
        }

    targets = Targets()
    by_setting: dict[str, list[str]] = {label: [] for label, _, _ in SETTINGS}  # fleets each one wins
    md = [f"Paired seeds 0..{args.seeds - 1}, {args.duration_s:g} s each; Δ = setting − EDF, mean ± 95 % half-width.\n"]
    for preset, mix in FLEETS:
        edf = runs[(preset, mix, "EDF", 1.0)]
        md += [
            f"\n**{preset}, {mix}, N=10** (EDF: fast {edf[:, 0].mean():.2f} %, slow {edf[:, 1].mean():.2f} %)\n",
            "| setting | fast % | slow % | Δ fast | Δ slow | vs EDF |",
            "|---|---|---|---|---|---|",
        ]
        wins = []
        for label, _, _, w in who[1:]:
            r = runs[(preset, mix, label, w)]
            (df, hf), (ds, hs) = interval(r[:, 0] - edf[:, 0]), interval(r[:, 1] - edf[:, 1])
            verdict = ""
            if df < 0 and ds <= 0:
                wins.append(f"{label} w={w:g}")
                significant = df + hf < 0 and ds + hs <= 0
                verdict = "wins both tiers" + (" (significant)" if significant else "")
                by_setting[label].append(f"{preset} {mix} w={w:g}" + (" (significant)" if significant else ""))
            md.append(
                f"| {label} w={w:g} | {r[:, 0].mean():.2f} | {r[:, 1].mean():.2f} | "
                f"{df:+.2f} ± {hf:.2f} | {ds:+.2f} ± {hs:.2f} | {verdict} |"
            )
        targets.check_min(f"some rollout setting beats EDF on both tiers: {preset} {mix} N=10", float(bool(wins)), 1.0)
        md.append("\nWins: " + (", ".join(wins) if wins else "**none**"))
    md.append("\n**Which setting wins where** (at some weight; a fleet may be won at several):\n")
    for label, _, _ in SETTINGS:
        won = by_setting[label]
        fleets = {" ".join(w.split()[:2]) for w in won}
        md.append(f"- {label}: {len(fleets)} of {len(FLEETS)} fleets" + (f" ({'; '.join(won)})" if won else ""))
    text = "\n".join(md) + "\n"
    print(text)
    if args.out:
        Path(args.out).write_text("# N = 10 per-tier starvation against EDF, paired seeds\n\n" + text)
        print(f"wrote {args.out}")
    targets.finish()


if __name__ == "__main__":
    main()
