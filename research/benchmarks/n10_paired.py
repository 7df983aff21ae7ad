"""N = 10 per-tier starvation against EDF with paired seeds and 95 % confidence intervals.

``research/benchmarks/frontier.py`` and the frontier study (``python -m armory_research.frontier``) compare tier means over a few seeds,
where a difference of a few tenths of a point can be noise. Here every setting runs on the same
seeds as EDF (same network draws), and each difference is reported as the mean of the per-seed
differences ± 1.96 standard errors, so a reader can tell a win from a tie.

Settings, each at several fast-robot weights: Rollout with the ``same`` base policy
(``rollout_same`` of ``armory_research.variants``: its rollouts keep dispatching batches the size
of the candidate; the setting the frontier study recommends and ``research/benchmarks/frontier.py``
checks on the small fleets) and Rollout as registered. (Rollout ordering its later batches by
weighted coverage gain was measured too, at commit 8588e12, and left off the product.) Fleets:
libero and piper, one-fast and half-fast, N = 10.

Target (exits 1 on a miss), the issue's, for the checked setting (``rollout_same``): in every fleet
it is, at some weight, at least as good as EDF on both tiers' mean starvation and strictly better
on the fast tier. The table also marks a win whose confidence intervals exclude a loss on both
tiers (``significant``), and says which fleets the other settings win.

Run: ``.venv/bin/python research/benchmarks/n10_paired.py [--seeds=48] [--first_seed=0] [--duration_s=120] [--out=FILE.md]``
(``--first_seed=1000`` re-checks the weights on seeds they were not picked on)
(about 20 minutes on 2 cores with the defaults).
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
from _study import Targets  # noqa: E402

from lerobot_armory.schedulers import make_scheduler_config  # noqa: E402
from lerobot_armory.sim.run import SimConfig, simulate  # noqa: E402

FLEETS = [("libero", "one-fast"), ("libero", "half-fast"), ("piper", "one-fast"), ("piper", "half-fast")]
# (label, scheduler, fast-robot weights)
SETTINGS: list[tuple[str, str, tuple[float, ...]]] = [
    ("rollout same", "rollout_same", (1.75, 2.0, 2.25, 2.5, 3.0, 3.25, 3.3)),  # the checked one
    ("rollout", "rollout", (1.75, 2.0, 2.1, 2.25, 2.5, 3.0)),
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
    ap.add_argument("--first_seed", type=int, default=0, help="seeds first_seed .. first_seed + seeds - 1")
    ap.add_argument("--duration_s", type=float, default=120.0)
    ap.add_argument("--out", help="also write the tables to this markdown file")
    ap.add_argument("--plot", help="also draw each fleet's trade-off (fast vs slow tier) to this PNG")
    ap.add_argument("--only", help="run EDF and this one setting (its label, e.g. 'rollout same')")
    args = ap.parse_args()
    settings = [st for st in SETTINGS if args.only in (None, st[0])]
    if not settings:
        sys.exit(f"--only: no setting labelled {args.only!r} (have: {', '.join(st[0] for st in SETTINGS)})")

    who = [("EDF", "edf", {}, 1.0)]
    who += [(label, name, {}, w) for label, name, weights in settings for w in weights]
    jobs = [
        (preset, mix, name, opts, w, seed, args.duration_s)
        for preset, mix in FLEETS
        for _, name, opts, w in who
        for seed in range(args.first_seed, args.first_seed + args.seeds)
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
    by_setting: dict[str, list[str]] = {label: [] for label, _, _ in settings}  # fleets each one wins
    md = [f"Paired seeds {args.first_seed}..{args.first_seed + args.seeds - 1}, {args.duration_s:g} s each; Δ = setting − EDF, mean ± 95 % half-width.\n"]
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
        if SETTINGS[0] in settings:  # the target is the checked setting's (--only may leave it out)
            checked = [x for x in wins if x.startswith(f"{SETTINGS[0][0]} w=")]
            targets.check_min(f"{SETTINGS[0][0]} beats EDF on both tiers at some weight: {preset} {mix} N=10", float(bool(checked)), 1.0)
        md.append("\nWins: " + (", ".join(wins) if wins else "**none**"))
    md.append("\n**Which setting wins where** (at some weight; a fleet may be won at several):\n")
    for label, _, _ in settings:
        won = by_setting[label]
        fleets = {" ".join(w.split()[:2]) for w in won}
        md.append(f"- {label}: {len(fleets)} of {len(FLEETS)} fleets" + (f" ({'; '.join(won)})" if won else ""))
    text = "\n".join(md) + "\n"
    print(text)
    if args.out:
        Path(args.out).write_text("# N = 10 per-tier starvation against EDF, paired seeds\n\n" + text)
        print(f"wrote {args.out}")
    if args.plot:
        plot(runs, settings, Path(args.plot))
        print(f"wrote {args.plot}")
    targets.finish()


ZOOM_PP = (5.0, 8.0)  # fast, slow: how far from EDF a point may be and still set a panel's zoom


def plot(runs: dict[tuple, np.ndarray], settings: list[tuple[str, dict[str, str], tuple[float, ...]]], out: Path) -> None:
    """One panel per fleet: EDF's point, each setting's weight curve (mean fast / slow starvation),
    the 95 % half-widths of the paired differences as error bars, significant wins filled. Each
    panel is zoomed on the points within ZOOM_PP of EDF (the others are off the panel)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, grid = plt.subplots(2, 2, figsize=(11.5, 9.5))
    colors = ["tab:red", "tab:purple", "tab:blue", "tab:orange"]
    for ax, (preset, mix) in zip(grid.flat, FLEETS, strict=True):
        edf = runs[(preset, mix, "EDF", 1.0)]
        ef, es = edf[:, 0].mean(), edf[:, 1].mean()
        near = [(ef, es)]
        for color, (label, _, weights) in zip(colors, settings, strict=False):
            xs, ys = [], []
            for w in weights:
                r = runs[(preset, mix, label, w)]
                (df, hf), (ds, hs) = interval(r[:, 0] - edf[:, 0]), interval(r[:, 1] - edf[:, 1])
                x, y = ef + df, es + ds
                xs.append(x)
                ys.append(y)
                significant = df + hf < 0 and ds + hs <= 0
                ax.errorbar(x, y, xerr=hf, yerr=hs, fmt="o", ms=5, color=color, mfc=color if significant else "white", lw=0.8)
                ax.annotate(f"{w:g}", (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7, color=color)
            ax.plot(xs, ys, "-", color=color, lw=0.8, label=f"{label} (w)")
            near.extend((x, y) for x, y in zip(xs, ys, strict=True) if abs(x - ef) <= ZOOM_PP[0] and abs(y - es) <= ZOOM_PP[1])
        ax.plot(ef, es, "D", color="black", ms=8, label="EDF")
        ax.axvline(ef, color="black", lw=0.6, ls=":")
        ax.axhline(es, color="black", lw=0.6, ls=":")
        px = max(0.5, 0.1 * (max(x for x, _ in near) - min(x for x, _ in near)))
        py = max(0.3, 0.1 * (max(y for _, y in near) - min(y for _, y in near)))
        ax.set_xlim(min(x for x, _ in near) - px, max(x for x, _ in near) + px)
        ax.set_ylim(min(y for _, y in near) - py, max(y for _, y in near) + py)
        lo_x, lo_y = ax.get_xlim()[0], ax.get_ylim()[0]
        ax.fill_between([lo_x, ef], lo_y, es, color="tab:green", alpha=0.08, label="beats EDF on both")
        ax.set_title(f"{preset}, {mix}, N=10", fontsize=9)
        ax.set_xlabel("fast-tier starvation %")
        ax.set_ylabel("slow-tier starvation %")
        ax.grid(alpha=0.3)
    grid.flat[0].legend(fontsize=7)
    fig.suptitle(
        "N=10, paired seeds: filled = significant win on both tiers (95 % half-widths as bars);\n"
        f"zoomed to within {ZOOM_PP[0]:g} pp (fast) / {ZOOM_PP[1]:g} pp (slow) of EDF"
    )
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
