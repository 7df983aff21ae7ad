"""The frontier study: how far RR, EDF, Lookahead and Rollout are from the best schedule.

Three parts, each a grid of independent jobs on a process pool:

- ``optimum``: for every small fleet (both presets × three mixes × N = 2..6) the deterministic
  episode of :mod:`armory_research.optimal` (σ = 0, synchronous cold start) is solved exactly
  at the longest horizon the search finishes within its budget (5 s first, else the ladder
  1, 1.5, 2, 2.5, 3, 4 s upwards until a horizon is cut off); every scheduler plays the same
  episode and its executed robot time is reported as a fraction of the optimum. Where 5 s is not
  exact, the 5 s bracket is reported too: the best schedule found, and the tighter of the
  search's proven upper bound and the Lagrangian device-pricing bound of
  :mod:`armory_research.bound` (``full`` profile), with every scheduler as % of it.
- ``fleet``: the simulator (preset network with jitter, several seeds) for N = 2..10, every
  scheduler, per-tier starvation.
- ``pareto``: N = 10, one-fast and half-fast, both presets: fast- vs slow-tier starvation of every
  scheduler and weight, and the per-tier comparison of the new scheduler against EDF.

Outputs in ``OUT_DIR``: ``fraction_of_optimum.{csv,md}``, ``starvation_vs_fleet.csv``,
``starvation_vs_fleet_<preset>.png``, ``pareto.{csv,png}``, ``n10_comparison.md`` and
``COMMAND.md``. Profiles: ``full`` (the committed results, about 15 min on 2 cores) and
``quick`` (a small subset for a smoke test).

Run from the repository root: ``PYTHONPATH=research .venv/bin/python -m armory_research.frontier
--profile=full --out_dir=docs/results/frontier --workers=2`` (``make research-frontier``).
"""

from __future__ import annotations

import csv
import json
import os
import shlex
import sys
import time
from collections import defaultdict
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_armory.cli_util import parse_or_exit, run_or_exit
from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import load_profile
from lerobot_armory.schedulers import make_scheduler_config
from lerobot_armory.sim.presets import MIXES, get_preset
from lerobot_armory.sim.run import SimConfig, run_label, simulate

from armory_research.bound import lagrangian_bound, time_priced_bound
from armory_research.optimal import Episode, EpisodeResult, episode_for, play, solve

# How the study is invoked (there is no console script: research/ is not part of the installed package).
PROG = "python -m armory_research.frontier"

# The new scheduler of this study and the label family it gets in tables and plots.
NEW = "rollout"
PARTS = ("optimum", "fleet", "pareto")


@dataclass(frozen=True)
class Contender:
    """A scheduler as compared here: registered name, fast-robot weight, label."""

    name: str
    weight: float

    @property
    def label(self) -> str:
        return run_label(self.name, self.weight)


def contenders(new_weights: Sequence[float], la_weights: Sequence[float] = (1.0, 3.0, 5.0)) -> list[Contender]:
    """RR, EDF, LA at ``la_weights`` and the new scheduler at ``new_weights``."""
    out = [Contender("rr", 1.0), Contender("edf", 1.0)]
    out += [Contender("lookahead", w) for w in la_weights]
    out += [Contender(NEW, w) for w in new_weights]
    return out


@dataclass(frozen=True)
class FrontierProfile:
    """Grid and budgets of one frontier run.

    Attributes:
        presets / mixes / small_sizes: the small fleets solved to optimality.
        horizon_s: the horizon tried first for every small fleet.
        ladder_s: shorter horizons tried, upwards, when ``horizon_s`` is not solved in budget.
        first_budget_s / ladder_budget_s: search time for the ``horizon_s`` try / each ladder step.
        table_weights: new-scheduler weights played on the small fleets (objective weight 1).
        fleet_sizes / fleet_seeds / fleet_duration_s / fleet_weights: the starvation-vs-N sweep.
        pareto_robots / pareto_seeds / pareto_duration_s / pareto_la_weights / pareto_new_weights:
            the N = 10 tier trade-off.
        lagrangian: where the exact search does not finish at ``horizon_s``, also compute the
            Lagrangian upper bounds there (flat price: seconds; per-slot prices: one to three
            minutes per fleet) for the full-horizon bracket.
    """

    presets: tuple[str, ...]
    mixes: tuple[str, ...]
    small_sizes: tuple[int, ...]
    horizon_s: float
    ladder_s: tuple[float, ...]
    first_budget_s: float
    ladder_budget_s: float
    table_weights: tuple[float, ...]
    fleet_sizes: tuple[int, ...]
    fleet_seeds: int
    fleet_duration_s: float
    fleet_weights: tuple[float, ...]
    pareto_robots: int
    pareto_seeds: int
    pareto_duration_s: float
    pareto_la_weights: tuple[float, ...]
    pareto_new_weights: tuple[float, ...]
    lagrangian: bool = False


PROFILES: dict[str, FrontierProfile] = {
    "full": FrontierProfile(
        presets=("libero", "piper"),
        mixes=MIXES,
        small_sizes=(2, 3, 4, 5, 6),
        horizon_s=5.0,
        ladder_s=(1.0, 1.5, 2.0, 2.5, 3.0, 4.0),
        first_budget_s=10.0,
        ladder_budget_s=30.0,
        table_weights=(1.0,),
        fleet_sizes=(2, 4, 6, 8, 10),
        fleet_seeds=2,
        fleet_duration_s=120.0,
        fleet_weights=(1.0, 3.0),
        pareto_robots=10,
        pareto_seeds=3,
        pareto_duration_s=120.0,
        pareto_la_weights=(1.0, 2.0, 3.0, 4.0, 5.0),
        pareto_new_weights=(1.0, 1.5, 1.75, 2.0, 2.1, 2.25, 2.5, 3.0, 3.5, 4.0, 5.0),
        lagrangian=True,
    ),
    "quick": FrontierProfile(
        presets=("libero", "piper"),
        mixes=("one-fast",),
        small_sizes=(2, 3),
        horizon_s=2.0,
        ladder_s=(1.0,),
        first_budget_s=5.0,
        ladder_budget_s=5.0,
        table_weights=(1.0,),
        fleet_sizes=(2, 6),
        fleet_seeds=1,
        fleet_duration_s=20.0,
        fleet_weights=(1.0,),
        pareto_robots=6,
        pareto_seeds=1,
        pareto_duration_s=20.0,
        pareto_la_weights=(1.0, 3.0),
        pareto_new_weights=(1.0, 3.0),
    ),
}


@dataclass
class FrontierConfig:
    """Options of ``python -m armory_research.frontier``.

    Attributes:
        profile: ``full`` (the committed results) or ``quick`` (a smoke test).
        out_dir: where the tables, CSVs and figures go.
        workers: parallel processes (default: number of CPUs).
        parts: comma-separated subset of optimum,fleet,pareto.
    """

    profile: str = "full"
    out_dir: str = "out/frontier"
    workers: int | None = None
    parts: str = "optimum,fleet,pareto"


# --------------------------------------------------------------------------------------------
# Part 1: fraction of the optimum on small fleets


def weighted_value(result: EpisodeResult, weights: Sequence[float]) -> float:
    """A schedule's executed time on ``result.episode`` scored with ``weights`` (per robot)."""
    specs = result.episode.specs
    return sum(w * n / s.fps for w, s, n in zip(weights, specs, result.executed_steps, strict=True))


def play_contender(preset: str, mix: str, robots: int, horizon_s: float, who: Contender) -> EpisodeResult:
    """``who`` on the deterministic episode (its weight only changes what the scheduler sees)."""
    ep = episode_for(preset, mix, robots, horizon_s, fast_weight=who.weight)
    scheduler = make_scheduler_config(who.name).make(load_profile(get_preset(preset).latency_profile), ep.max_batch_size)
    return play(ep, scheduler)


def optimum_job(job: dict[str, Any]) -> dict[str, Any]:
    """Solve one small fleet (objective: every robot weighs 1) and play every contender on it."""
    preset, mix, n = job["preset"], job["mix"], job["robots"]
    prof: FrontierProfile = PROFILES[job["profile"]]
    who = contenders(prof.table_weights)
    started = time.perf_counter()

    def attempt(horizon: float, budget: float) -> tuple[Episode, dict[str, EpisodeResult], Any]:
        ep = episode_for(preset, mix, n, horizon)
        played = {c.label: play_contender(preset, mix, n, horizon, c) for c in who}
        ones = [1.0] * n
        best = max(played.values(), key=lambda r: weighted_value(r, ones))
        # The incumbent must be scored with the objective's weights (all 1).
        res = solve(ep, weighted_value(best, ones), best.batches, time_limit_s=budget)
        return ep, played, res

    tries: list[dict[str, Any]] = []
    ep, played, res = attempt(prof.horizon_s, prof.first_budget_s)
    tries.append(_try_row(prof.horizon_s, res))
    bracket: dict[str, Any] = {}
    if not res.exact:
        # The full horizon is out of the exact search's reach: bracket its optimum between the
        # best schedule found and the tighter proven upper bound (the search's own, and with
        # ``lagrangian`` the device-pricing bound of armory_research.bound).
        ones = [1.0] * n
        bracket = {
            "bracket_horizon_s": prof.horizon_s,
            "bracket_lower": res.value,
            "bracket_bb_upper": res.upper_bound,
            "bracket_upper": res.upper_bound,
            "bracket_values": {lab: weighted_value(r, ones) for lab, r in played.items()},
        }
        if prof.lagrangian:
            lag = lagrangian_bound(ep)
            # Per-slot prices from the flat one's optimum, aimed at the best schedule found.
            timed = time_priced_bound(ep, res.value, lag)
            bracket["bracket_lagrangian_upper"] = lag.upper_bound
            bracket["bracket_time_priced_upper"] = timed.upper_bound
            bracket["bracket_upper"] = min(res.upper_bound, lag.upper_bound, timed.upper_bound)
    final = (prof.horizon_s, played, res) if res.exact else None
    if final is None:
        for horizon in prof.ladder_s:
            if horizon >= prof.horizon_s:
                break
            ep, played, res = attempt(horizon, prof.ladder_budget_s)
            tries.append(_try_row(horizon, res))
            if not res.exact:
                break
            final = (horizon, played, res)
    row: dict[str, Any] = {"preset": preset, "mix": mix, "robots": n, "tries": tries, "wall_s": 0.0}
    if final is not None:
        horizon, played, res = final
        ones = [1.0] * n
        row.update(
            horizon_s=horizon,
            optimum=res.value,
            exact=True,
            nodes=res.nodes,
            ceiling=episode_for(preset, mix, n, horizon).max_weighted_s(),
            values={lab: weighted_value(r, ones) for lab, r in played.items()},
        )
    else:  # not even the shortest horizon: keep the best bracket as the result
        ones = [1.0] * n
        row.update(
            horizon_s=tries[-1]["horizon_s"],
            optimum=res.value,
            upper_bound=res.upper_bound,
            exact=False,
            nodes=res.nodes,
            ceiling=episode_for(preset, mix, n, tries[-1]["horizon_s"]).max_weighted_s(),
            values={lab: weighted_value(r, ones) for lab, r in played.items()},
        )
    row.update(bracket)
    row["wall_s"] = time.perf_counter() - started
    return row


def _try_row(horizon: float, res: Any) -> dict[str, Any]:
    return {
        "horizon_s": horizon,
        "exact": res.exact,
        "value": res.value,
        "upper_bound": res.upper_bound,
        "nodes": res.nodes,
        "seconds": res.seconds,
    }


OPT_FIELDS = [
    "preset", "mix", "robots", "horizon_s", "exact", "optimum", "upper_bound", "ceiling", "scheduler",
    "value", "fraction", "bracket_horizon_s", "bracket_lower", "bracket_bb_upper", "bracket_lagrangian_upper",
    "bracket_time_priced_upper", "bracket_upper", "bracket_value", "bracket_fraction", "nodes",
]  # fmt: skip


def reference(r: dict[str, Any]) -> float:
    """What fractions are taken of: the optimum when exact, else its proven upper bound (so a
    fraction is never flattered by a search that was cut off)."""
    return r["optimum"] if r["exact"] else r["upper_bound"]


def optimum_rows(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One CSV row per (fleet, scheduler); ``optimum`` is the best schedule found, ``fraction`` is
    of :func:`reference`."""
    rows = []
    for r in sorted(results, key=lambda r: (r["preset"], MIXES.index(r["mix"]), r["robots"])):
        for label, value in r["values"].items():
            row = {k: r.get(k, "") for k in OPT_FIELDS}
            row.update(scheduler=label, value=round(value, 6), fraction=round(value / reference(r), 6))
            row["upper_bound"] = round(r.get("upper_bound", r["optimum"]), 6)
            row["optimum"] = round(r["optimum"], 6)
            row["ceiling"] = round(r["ceiling"], 6)
            if label in r.get("bracket_values", {}):
                v5 = r["bracket_values"][label]
                row.update(bracket_value=round(v5, 6), bracket_fraction=round(v5 / r["bracket_upper"], 6))
            rows.append(row)
    return rows


def optimum_markdown(results: list[dict[str, Any]], labels: Sequence[str]) -> str:
    """The fraction-of-optimum table (one row per fleet, one column per scheduler)."""
    head = "| preset | mix | N | horizon | optimum, robot-s | " + " | ".join(labels) + " |"
    lines = [head, "|" + "---|" * (5 + len(labels))]
    for r in sorted(results, key=lambda r: (r["preset"], MIXES.index(r["mix"]), r["robots"])):
        kind = "exact" if r["exact"] else f"≥ {r['optimum']:.2f}, % of bound"
        ref = reference(r)
        cells = []
        best_online = max(r["values"][lab] for lab in labels)
        for lab in labels:
            f = r["values"][lab] / ref
            cell = f"{100 * f:.1f}"
            if r["values"][lab] >= best_online - 1e-9:
                cell = f"**{cell}**"
            cells.append(cell)
        lines.append(
            f"| {r['preset']} | {r['mix']} | {r['robots']} | {r['horizon_s']:g} s | {ref:.2f} {kind} | "
            + " | ".join(cells)
            + " |"
        )
    brackets = [r for r in results if "bracket_upper" in r]
    text = "\n".join(lines)
    if brackets:
        text += (
            "\n\nFull horizon where the exact search did not finish: the optimum lies between the best "
            "schedule found and the tightest proven upper bound (branch-and-bound's, or the Lagrangian "
            "device-pricing bounds of `armory_research.bound`: one flat price, or one price per 5 ms slot). Each scheduler as % of the upper bound "
            "(a lower bound on its fraction of the optimum) · and the new scheduler as % of the best schedule found:\n\n"
        )
        text += (
            "| preset | mix | N | horizon | best found | B&B bound | flat-price bound | slot-price bound | gap | "
            + " | ".join(labels)
            + f" | {labels[-1]} / best found |\n"
        )
        text += "|" + "---|" * (10 + len(labels)) + "\n"
        for r in sorted(brackets, key=lambda r: (r["preset"], MIXES.index(r["mix"]), r["robots"])):
            lo, hi = r["bracket_lower"], r["bracket_upper"]
            vals = r.get("bracket_values", {})
            cells = [f"{100 * vals[lab] / hi:.1f}" if lab in vals else "" for lab in labels]
            new = f"{100 * vals[labels[-1]] / lo:.1f}" if labels[-1] in vals else ""
            text += (
                f"| {r['preset']} | {r['mix']} | {r['robots']} | {r['bracket_horizon_s']:g} s | {lo:.2f} | "
                f"{r.get('bracket_bb_upper', hi):.2f} | {r.get('bracket_lagrangian_upper', float('nan')):.2f} | "
                f"{r.get('bracket_time_priced_upper', float('nan')):.2f} | "
                f"{100 * (hi - lo) / hi:.1f} % | " + " | ".join(cells) + f" | {new} |\n"
            )
    return text


# --------------------------------------------------------------------------------------------
# Parts 2 and 3: the simulator (jitter, seeds)


def sim_job(job: dict[str, Any]) -> dict[str, Any]:
    """One simulated run (the sweep's record schema) plus the part it belongs to."""
    cfg = SimConfig(
        preset=job["preset"],
        mix=job["mix"],
        robots=job["robots"],
        scheduler=make_scheduler_config(job["scheduler"]),
        fast_weight=job["weight"],
        duration_s=job["duration_s"],
    ).resolved()
    record = simulate(cfg, job["seed"])
    record["group"] = job["part"]
    return record


def fleet_jobs(prof: FrontierProfile) -> list[dict[str, Any]]:
    jobs = []
    who = contenders(prof.fleet_weights)
    for preset in prof.presets:
        for mix in MIXES:
            for n in prof.fleet_sizes:
                for c in who:
                    for seed in range(prof.fleet_seeds):
                        jobs.append(
                            {"part": "fleet", "preset": preset, "mix": mix, "robots": n, "scheduler": c.name,
                             "weight": c.weight, "duration_s": prof.fleet_duration_s, "seed": seed}
                        )  # fmt: skip
    return jobs


def pareto_jobs(prof: FrontierProfile) -> list[dict[str, Any]]:
    jobs = []
    who = contenders(prof.pareto_new_weights, prof.pareto_la_weights)
    for preset in prof.presets:
        for mix in ("one-fast", "half-fast"):
            for c in who:
                for seed in range(prof.pareto_seeds):
                    jobs.append(
                        {"part": "pareto", "preset": preset, "mix": mix, "robots": prof.pareto_robots,
                         "scheduler": c.name, "weight": c.weight, "duration_s": prof.pareto_duration_s, "seed": seed}
                    )  # fmt: skip
    return jobs


def tier_means(records: list[dict[str, Any]]) -> dict[tuple, dict[str, float]]:
    """(preset, mix, N, scheduler, weight) -> mean fast/slow/avg starvation over seeds."""
    acc: dict[tuple, list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        acc[(r["preset"], r["mix"], r["robots"], r["scheduler"], r["fast_weight"])].append(r)
    out = {}
    for key, rows in acc.items():
        out[key] = {
            "fast": float(np.mean([x["tiers"]["fast"]["starvation_pct"] for x in rows])) if "fast" in rows[0]["tiers"] else float("nan"),
            "slow": float(np.mean([x["tiers"]["slow"]["starvation_pct"] for x in rows])) if "slow" in rows[0]["tiers"] else float("nan"),
            "avg": float(np.mean([x["avg_starvation_pct"] for x in rows])),
            "seeds": len(rows),
            "label": rows[0]["label"],
            "decision_ms_p99": max(x["decision_ms_p99"] for x in rows),
        }
    return out


def n10_comparison(records: list[dict[str, Any]]) -> tuple[str, list[dict[str, Any]]]:
    """Per preset and mix: EDF against every new-scheduler weight; the verdict of the target
    (at least as good as EDF on both tiers at some weight, strictly better on the fast tier)."""
    means = tier_means(records)
    verdicts = []
    lines = []
    for preset in sorted({k[0] for k in means}):
        for mix in ("one-fast", "half-fast"):
            keys = [k for k in means if k[0] == preset and k[1] == mix]
            if not keys:
                continue
            n = keys[0][2]
            edf = next((means[k] for k in keys if k[3] == "edf"), None)
            if edf is None:
                continue
            lines.append(f"\n**{preset}, {mix}, N={n}** (fast / slow starvation %, mean of {edf['seeds']} seeds)\n")
            lines.append("| scheduler | fast % | slow % | avg % | vs EDF |")
            lines.append("|---|---|---|---|---|")
            winners = []
            for k in sorted(keys, key=lambda k: (k[3] != "rr", k[3] != "edf", k[3] != "lookahead", k[4])):
                m = means[k]
                tag = ""
                if k[3] != "edf":
                    fast_better = m["fast"] < edf["fast"]
                    slow_ok = m["slow"] <= edf["slow"]
                    tag = "wins both tiers" if fast_better and slow_ok else (
                        "fast better, slow worse" if fast_better else ("slow better, fast worse" if slow_ok else "worse on both")
                    )
                    if k[3] == NEW and fast_better and slow_ok:
                        winners.append((k[4], m))
                lines.append(f"| {m['label']} | {m['fast']:.2f} | {m['slow']:.2f} | {m['avg']:.2f} | {tag} |")
            verdicts.append(
                {"preset": preset, "mix": mix, "robots": n, "edf_fast": edf["fast"], "edf_slow": edf["slow"],
                 "winning_weights": [w for w, _ in winners]}
            )  # fmt: skip
            lines.append(
                f"\nTarget ({NEW} ≤ EDF on both tiers, < on fast, at some weight): "
                + (f"met at w = {', '.join(f'{w:g}' for w, _ in winners)}" if winners else "**not met**")
            )
    return "\n".join(lines).lstrip("\n") + "\n", verdicts


# --------------------------------------------------------------------------------------------
# Figures


def plot_pareto(records: list[dict[str, Any]], out: Path) -> Path:
    """Fast- vs slow-tier starvation of every scheduler and weight (N = 10, one panel per fleet)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    means = tier_means(records)
    panels = sorted({(k[0], k[1], k[2]) for k in means}, key=lambda p: (p[0], p[1] != "one-fast"))
    cols = 2 if len(panels) > 2 else len(panels)
    rows_n = (len(panels) + cols - 1) // cols
    fig, grid = plt.subplots(rows_n, cols, figsize=(5.6 * cols, 4.6 * rows_n), squeeze=False)
    axes = [[ax for row in grid for ax in row]]
    for ax in axes[0][len(panels):]:
        ax.set_visible(False)
    style = {"rr": ("s", "tab:gray"), "edf": ("D", "black"), "lookahead": ("o", "tab:blue"), NEW: ("^", "tab:red")}
    for ax, (preset, mix, n) in zip(axes[0], panels, strict=False):
        keys = [k for k in means if k[:3] == (preset, mix, n)]
        for name in ("lookahead", NEW):
            line = sorted((k for k in keys if k[3] == name), key=lambda k: k[4])
            if line:
                xs = [means[k]["fast"] for k in line]
                ys = [means[k]["slow"] for k in line]
                marker, color = style[name]
                ax.plot(xs, ys, "-", marker=marker, color=color, label="LA (w)" if name == "lookahead" else f"{NEW} (w)")
                for k, x, y in zip(line, xs, ys, strict=True):
                    ax.annotate(f"{k[4]:g}", (x, y), textcoords="offset points", xytext=(4, 3), fontsize=7, color=color)
        for name in ("rr", "edf"):
            for k in keys:
                if k[3] == name:
                    marker, color = style[name]
                    ax.plot(means[k]["fast"], means[k]["slow"], marker, color=color, ms=8, label=means[k]["label"])
        edf = next((means[k] for k in keys if k[3] == "edf"), None)
        if edf is not None:  # the region that beats EDF on both tiers
            ax.axvline(edf["fast"], color="black", lw=0.6, ls=":")
            ax.axhline(edf["slow"], color="black", lw=0.6, ls=":")
            ax.fill_between([0, edf["fast"]], 0, edf["slow"], color="tab:green", alpha=0.08, label="beats EDF on both")
        ax.set_xlim(left=0)
        ax.set_ylim(bottom=0)
        ax.set_title(f"{preset}, {mix}, N={n}", fontsize=9)
        ax.set_xlabel("fast-tier starvation %")
        ax.set_ylabel("slow-tier starvation %")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.suptitle("Tier trade-off: where each scheduler and weight lands (lower-left is better)")
    fig.tight_layout()
    path = out / "pareto.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------------------------
# Driver


@dataclass
class FrontierResults:
    """What :func:`run` produced (also written to disk)."""

    optimum: list[dict[str, Any]] = field(default_factory=list)
    fleet: list[dict[str, Any]] = field(default_factory=list)
    pareto: list[dict[str, Any]] = field(default_factory=list)
    verdicts: list[dict[str, Any]] = field(default_factory=list)


def run(cfg: FrontierConfig) -> FrontierResults:
    """Run the requested parts, write every output, print the tables."""
    if cfg.profile not in PROFILES:
        raise ConfigError("profile", f"unknown frontier profile {cfg.profile!r}; known: {', '.join(PROFILES)}")
    parts = [p.strip() for p in cfg.parts.split(",") if p.strip()]
    for p in parts:
        if p not in PARTS:
            raise ConfigError("parts", f"unknown part {p!r}; known: {', '.join(PARTS)}")
    prof = PROFILES[cfg.profile]
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    workers = cfg.workers or os.cpu_count() or 1
    started = time.perf_counter()

    opt_jobs = []
    if "optimum" in parts:
        opt_jobs = [
            {"profile": cfg.profile, "preset": p, "mix": m, "robots": n}
            for p in prof.presets
            for m in prof.mixes
            for n in prof.small_sizes
        ]
        # Longest first (the big fleets), so the pool ends evenly.
        opt_jobs.sort(key=lambda j: -j["robots"])
    sim = (fleet_jobs(prof) if "fleet" in parts else []) + (pareto_jobs(prof) if "pareto" in parts else [])
    print(
        f"frontier profile={cfg.profile}: {len(opt_jobs)} optimum searches + {len(sim)} simulated runs "
        f"on {workers} worker(s) -> {out}/",
        file=sys.stderr,
    )
    results = FrontierResults()
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = {pool.submit(optimum_job, j): ("optimum", j) for j in opt_jobs}
        futures.update({pool.submit(sim_job, j): ("sim", j) for j in sim})
        done = 0
        for fut in as_completed(futures):
            kind, job = futures[fut]
            res = fut.result()
            done += 1
            if kind == "optimum":
                results.optimum.append(res)
                print(
                    f"[{done}/{len(futures)}] optimum {res['preset']} {res['mix']} N={res['robots']}: "
                    f"horizon {res['horizon_s']:g} s {'exact' if res['exact'] else 'bound'} ({res['wall_s']:.0f} s)",
                    file=sys.stderr,
                )
            else:
                (results.fleet if res["group"] == "fleet" else results.pareto).append(res)
    elapsed = time.perf_counter() - started

    text = []
    figures: list[Path] = []
    if results.optimum:
        labels = [c.label for c in contenders(prof.table_weights)]
        rows = optimum_rows(results.optimum)
        with open(out / "fraction_of_optimum.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=OPT_FIELDS)
            writer.writeheader()
            writer.writerows(rows)
        (out / "optimum_search.json").write_text(json.dumps(results.optimum, indent=1) + "\n")
        md = optimum_markdown(results.optimum, labels)
        (out / "fraction_of_optimum.md").write_text(
            "# Executed robot time as % of the best work-conserving schedule\n\n"
            "Deterministic episodes (σ = 0, preset median delay, synchronous cold start, l40s-pi05), "
            "objective: executed robot-seconds before the horizon (all robots weigh 1; LA w=3/5 still "
            "schedule with their weights). Horizon: 5 s where the search finished in budget, else the "
            "longest of 1, 1.5, 2, 2.5, 3, 4 s that did. Bold: best online scheduler. A row marked "
            "'% of bound' was not solved even at 1 s: its fractions are of the proven upper bound.\n\n" + md
        )
        text.append("== fraction of the optimum (%) ==\n" + md)
    if results.fleet:
        from lerobot_armory.sim.sweep_plots import plot_fleet
        from lerobot_armory.sim.sweep import CSV_FIELDS, csv_row

        with open(out / "starvation_vs_fleet.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
            writer.writeheader()
            writer.writerows(csv_row(r) for r in results.fleet)
        figures += plot_fleet(results.fleet, out)
    if results.pareto:
        from lerobot_armory.sim.sweep import CSV_FIELDS, csv_row

        with open(out / "pareto.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
            writer.writeheader()
            writer.writerows(csv_row(r) for r in results.pareto)
        figures.append(plot_pareto(results.pareto, out))
        md, results.verdicts = n10_comparison(results.pareto)
        (out / "n10_comparison.md").write_text("# Per-tier starvation at N = 10: the new scheduler against EDF\n\n" + md)
        text.append("== per-tier comparison ==\n" + md)
    command = "PYTHONPATH=research python -m armory_research.frontier " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    (out / "COMMAND.md").write_text(
        f"# How these results were made\n\n```\n{command}\n```\n\n"
        f"{len(results.optimum)} optimum searches and {len(results.fleet) + len(results.pareto)} simulated runs, "
        f"{elapsed:.0f} s wall on {workers} worker(s).\n"
    )
    print("\n\n".join(text))
    print(f"\ndone in {elapsed:.1f} s. Results in {out}/")
    for p in figures:
        print(f"  {p}")
    return results


def main(argv: list[str] | None = None) -> None:
    """Command-line entry point (``python -m armory_research.frontier``, ``research/`` on ``PYTHONPATH``)."""
    cfg = parse_or_exit(FrontierConfig, argv, PROG)
    run_or_exit(run, cfg, PROG)


if __name__ == "__main__":
    main()
