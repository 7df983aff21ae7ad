"""``lerobot-armory-plan``: how many GPUs does this fleet need?

Finds the fewest GPUs K whose simulated fast-tier starvation (mean over seeds) stays at or under
a target, for a fleet file or a preset shorthand::

    lerobot-armory-plan --fleet=examples/fleets/libero-half-fast-100.yaml --target_fast_pct=5
    lerobot-armory-plan --fleet=preset:piper:one-fast:40 --target_fast_pct=5 --figure=plan.png

The search starts at the placement load model's lower bound ``ceil(total demand)`` (every robot's
device seconds per second summed; :mod:`lerobot_armory.placement`), gallops upward (1, 2, 4...
more GPUs) until the target is met, or downward when the bound already meets it (EDF protects the
fast tier at the slow tier's expense, so the fast tier alone can fit on fewer GPUs than the whole
fleet's demand), then bisects. Starvation is not strictly monotone in K (placement granularity,
one draw per seed), so the answer is *verified*: K - 1 misses and K + 1 meets the target too;
if K + 1 misses, the search goes on above it. Every K tried is printed.

Each K is a :func:`~lerobot_armory.sim.cluster.simulate_cluster` per seed, with each distinct
replica composition simulated once per seed and reused across K (see that module). Exit status:
0 with an answer, 1 if even ``--max_gpus`` misses the target, 2 for a bad fleet file or option.
A fleet whose devices are shared by several policies (``policies:``) is planned on GPUs that
each serve every policy (each must hold every policy's weights): placement charges each robot its
own policy's ``d_infer``, and each GPU is simulated with one scheduler per policy and the
:class:`~lerobot_armory.arbiter.PolicyArbiter` between them, as ``lerobot-armory-sim --fleet``
simulates one such device. ``--latency_profile`` and ``--max_batch_size`` do not apply to it
(each policy names its own in the file). The targets then hold for every policy's robots, not
only for the fleet's mean: a cheap policy's robots must not hide another's starving.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_armory.cli_util import parse_or_exit, run_or_exit
from lerobot_armory.errors import ConfigError
from lerobot_armory.placement import PLACEMENTS
from lerobot_armory.sim.cluster import ClusterResult, simulate_cluster
from lerobot_armory.sim.fleet_file import Fleet, load_fleet, with_overrides

PROG = "lerobot-armory-plan"
# Above this many GPUs a plan is a data-centre question, not a simulation to run in seconds.
MAX_GPUS_LIMIT = 4096


@dataclass
class PlanConfig:
    """Options of ``lerobot-armory-plan``.

    Attributes:
        fleet: fleet file (YAML/JSON) or ``preset:NAME:MIX:N[:FAST_WEIGHT]``.
        target_fast_pct: fast-tier starvation (mean over seeds) the answer must stay under, %.
        target_slow_pct: optionally, the slow tier's too, %.
        placement: placement policy: random, round_robin, least_loaded, mirror_aware.
        max_gpus: the most GPUs to consider.
        seeds: seeds per K (seed, seed+1, ...): join order, placement and network draws.
        seed: first seed.
        duration_s: simulated seconds per replica.
        latency_profile: run the fleet on this GPU kind instead of the file's (built-in or JSON).
        max_batch_size: and/or with this batch cap.
        compare_placements: also simulate the other placements at the Ks tried (figure and table).
        figure: write the starvation-vs-K figure here (PNG).
        output: write the search as JSON here.
    """

    fleet: str = ""
    target_fast_pct: float = 5.0
    target_slow_pct: float | None = None
    placement: str = "mirror_aware"
    max_gpus: int = 64
    seeds: int = 2
    seed: int = 0
    duration_s: float = 30.0
    latency_profile: str | None = None
    max_batch_size: int | None = None
    compare_placements: bool = False
    figure: str | None = None
    output: str | None = None

    def check(self) -> None:
        """Every option on its own (ConfigError naming the first bad one)."""
        for name in ("target_fast_pct", "target_slow_pct"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and 0 <= value <= 100):
                raise ConfigError(name, f"must be a percentage in [0, 100], got {value}")
        if self.placement not in PLACEMENTS:
            raise ConfigError("placement", f"unknown placement {self.placement!r}; known: {', '.join(PLACEMENTS)}")
        if not 1 <= self.max_gpus <= MAX_GPUS_LIMIT:
            raise ConfigError("max_gpus", f"must be in [1, {MAX_GPUS_LIMIT}], got {self.max_gpus}")
        if not 1 <= self.seeds <= 100:
            raise ConfigError("seeds", f"must be in [1, 100], got {self.seeds}")
        if not (math.isfinite(self.duration_s) and 0 < self.duration_s <= 3600):
            raise ConfigError("duration_s", f"must be in (0, 3600] seconds, got {self.duration_s}")


@dataclass
class Point:
    """One K evaluated with one placement: the mean over seeds, and the cluster of each seed."""

    gpus: int
    placement: str
    runs: list[ClusterResult]
    placeable: bool = True

    def _mean(self, values: list[float]) -> float:
        values = [v for v in values if not math.isnan(v)]
        return float(np.mean(values)) if values else math.nan

    @property
    def fast_pct(self) -> float:
        return self._mean([r.tier_starvation_pct("fast") for r in self.runs]) if self.placeable else math.inf

    @property
    def slow_pct(self) -> float:
        return self._mean([r.tier_starvation_pct("slow") for r in self.runs]) if self.placeable else math.inf

    def policy_pct(self, policy: str, tier: str) -> float:
        """``policy``'s robots of ``tier``: starvation, mean over seeds (several policies per GPU)."""
        return self._mean([r.policy_tier_starvation_pct(policy, tier) for r in self.runs]) if self.placeable else math.inf

    @property
    def worst_fast_pct(self) -> float:
        return self._mean([r.worst_replica_pct("fast") for r in self.runs]) if self.placeable else math.inf

    @property
    def utilization_mean(self) -> float:
        return self._mean([float(np.mean(r.utilizations)) for r in self.runs])

    @property
    def utilization_max(self) -> float:
        return self._mean([max(r.utilizations) for r in self.runs])

    @property
    def wall_s(self) -> float:
        return sum(r.wall_s for r in self.runs)

    def record(self) -> dict[str, Any]:
        return {
            "gpus": self.gpus,
            "placement": self.placement,
            "placeable": self.placeable,
            "fast_pct": _num(self.fast_pct),
            "slow_pct": _num(self.slow_pct),
            "worst_replica_fast_pct": _num(self.worst_fast_pct),
            "policies": {p: {"fast_pct": _num(self.policy_pct(p, "fast")), "slow_pct": _num(self.policy_pct(p, "slow"))}
                         for p in (self.runs[0].policies if self.runs else [])},
            "per_seed": [
                {
                    "seed": r.seed,
                    "fast_pct": _num(r.tier_starvation_pct("fast")),
                    "slow_pct": _num(r.tier_starvation_pct("slow")),
                }
                for r in self.runs
            ],
            "utilization_mean": _num(self.utilization_mean) if self.runs else None,
            "utilization_max": _num(self.utilization_max) if self.runs else None,
            "robots_per_gpu": [
                min(min(r.robots_per_replica) for r in self.runs),
                max(max(r.robots_per_replica) for r in self.runs),
            ]
            if self.runs
            else None,
            "wall_s": self.wall_s,
        }


def _num(x: float) -> float | None:
    return None if (math.isnan(x) or math.isinf(x)) else round(x, 4)


def _pc(x: float) -> str:
    """``12.34 %`` or ``n/a`` (a tier without robots)."""
    return "n/a" if math.isnan(x) else f"{x:.2f} %"


def _pct(x: float, width: int = 0) -> str:
    """``12.34`` or ``n/a`` (a tier without robots), right-aligned in ``width``."""
    return f"{'n/a' if math.isnan(x) else f'{x:.2f}':>{width}}"


class Planner:
    """Evaluates K (cached) and searches for the fewest GPUs meeting the targets."""

    def __init__(self, fleet: Fleet, cfg: PlanConfig, quiet: bool = False) -> None:
        self.fleet, self.cfg, self.quiet = fleet, cfg, quiet
        self.cache: dict[Any, Any] = {}  # composition outcomes, shared by every K and placement
        self.points: dict[tuple[str, int], Point] = {}
        self.order: list[int] = []  # Ks in the order the search tried them
        self.has_fast = fleet.tier_counts()["fast"] > 0
        self.policies = [p.name for p in fleet.policies] if fleet.is_mixed else []

    def evaluate(self, gpus: int, placement: str | None = None, quiet: bool = False) -> Point:
        placement = placement or self.cfg.placement
        key = (placement, gpus)
        if key in self.points:
            return self.points[key]
        cfg, fleet = self.cfg, self.fleet
        if fleet.max_robots_per_gpu and gpus * fleet.max_robots_per_gpu < fleet.robots:
            point = Point(gpus, placement, [], placeable=False)
        else:
            runs = [
                simulate_cluster(fleet, gpus, placement, cfg.seed + s, cfg.duration_s, cache=self.cache)
                for s in range(cfg.seeds)
            ]
            point = Point(gpus, placement, runs)
        self.points[key] = point
        if placement == cfg.placement:
            self.order.append(gpus)
        if not (quiet or self.quiet):
            verdict = "meets" if self.meets(point) else "misses"
            what = (
                f"fast {_pc(point.fast_pct)}, slow {_pc(point.slow_pct)}, worst GPU fast {_pc(point.worst_fast_pct)}"
                + self.by_policy(point)
                if point.placeable
                else f"cannot place {fleet.robots} robots at {fleet.max_robots_per_gpu} per GPU"
            )
            print(
                f"[{PROG}] K={gpus:<4d} {placement}: {what} -> {verdict} ({point.wall_s:.2f} s)",
                file=sys.stderr,
                flush=True,
            )
        return point

    def by_policy(self, point: Point) -> str:
        """``; pi05 fast 4.1 %, act fast 0.2 %`` when several policies share each GPU, else empty."""
        parts = [f"{p} fast {_pc(point.policy_pct(p, 'fast'))}" for p in self.policies]
        return "; " + ", ".join(parts) if parts else ""

    def meets(self, point: Point) -> bool:
        """Whether ``point`` meets the targets: the fleet's tiers, and when several policies share
        each GPU, every policy's tiers too (a cheap policy's robots must not hide another's
        starving behind a fleet-wide mean)."""
        if not point.placeable:
            return False
        groups = [(point.fast_pct, point.slow_pct)]
        groups += [(point.policy_pct(p, "fast"), point.policy_pct(p, "slow")) for p in self.policies]
        return all(self._ok(fast, slow) for fast, slow in groups)

    def _ok(self, fast: float, slow: float) -> bool:
        fast_ok = not self.has_fast or not (fast > self.cfg.target_fast_pct)  # NaN: no fast robots here
        slow_ok = self.cfg.target_slow_pct is None or not (slow > self.cfg.target_slow_pct)
        return fast_ok and slow_ok

    def ok(self, gpus: int) -> bool:
        return self.meets(self.evaluate(gpus))

    def search(self, lower_bound: int) -> int | None:
        """The fewest GPUs meeting the targets, verified against its neighbours; None if max_gpus misses."""
        top = self.cfg.max_gpus
        start = min(max(1, lower_bound), top)
        if self.ok(start):
            lo, hi = 0, start  # lo: a K known to miss (0: none, every K >= 1 might meet)
            step = 1
            while hi - step >= 1:  # gallop down
                k = hi - step
                if self.ok(k):
                    hi, step = k, step * 2
                else:
                    lo = k
                    break
        else:
            lo, hi = start, None
        while True:
            if hi is None:  # gallop up from lo
                step = 1
                while True:
                    k = min(lo + step, top)
                    if self.ok(k):
                        hi = k
                        break
                    lo = k
                    if k == top:
                        return None
                    step *= 2
            while hi - lo > 1:  # bisect: lo misses, hi meets
                mid = (lo + hi) // 2
                if self.ok(mid):
                    hi = mid
                else:
                    lo = mid
            # Verify: one GPU more must meet too, or the answer was a lucky dip of a non-monotone curve.
            if hi == top or self.ok(hi + 1):
                return hi
            lo, hi = hi + 1, None


def run(cfg: PlanConfig) -> int:
    """Plan the fleet; prints progress to stderr and the answer and table to stdout. Returns the exit status."""
    cfg.check()
    fleet = load_fleet(cfg.fleet)
    fleet = with_overrides(fleet, cfg.latency_profile, cfg.max_batch_size)
    profile = fleet.profile()
    started = time.perf_counter()
    demand = fleet.total_demand()
    lower_bound = max(1, math.ceil(demand - 1e-9))
    print(f"[{PROG}] {fleet.describe()}", file=sys.stderr)
    served = [(p.profile(), p.max_batch_size) for p in fleet.policies] if fleet.is_mixed else [(profile, fleet.max_batch_size)]
    for prof, cap in served:
        if prof.is_extrapolated(cap):
            print(
                f"[{PROG}] note: {prof.name} is measured up to b={prof.measured_sizes}; larger batches are "
                "extrapolated linearly from the last two points",
                file=sys.stderr,
            )
    print(
        f"[{PROG}] load model: {demand:.2f} GPUs of device time -> start at K={min(lower_bound, cfg.max_gpus)}",
        file=sys.stderr,
    )
    planner = Planner(fleet, cfg)
    if not planner.has_fast:
        print(f"[{PROG}] note: the fleet has no fast robots; the fast-tier target holds trivially", file=sys.stderr)
    answer = planner.search(lower_bound)
    split = plan_split(fleet, cfg) if fleet.is_mixed else None
    if cfg.compare_placements:
        for name in PLACEMENTS:
            if name != cfg.placement:
                for k in sorted(set(planner.order)):
                    planner.evaluate(k, name, quiet=True)
    wall = time.perf_counter() - started
    seeds = list(range(cfg.seed, cfg.seed + cfg.seeds))
    target = f"fast-tier starvation ≤ {cfg.target_fast_pct:g} %"
    if cfg.target_slow_pct is not None:
        target += f" and slow-tier ≤ {cfg.target_slow_pct:g} %"
    gpu_kind = gpu_description(fleet)
    if answer is None:
        point = planner.points[(cfg.placement, cfg.max_gpus)]
        what = (
            f"fast {_pc(point.fast_pct)}, slow {_pc(point.slow_pct)}{planner.by_policy(point)}"
            if point.placeable
            else "the robots do not fit"
        )
        lines = [
            (
                f"even --max_gpus={cfg.max_gpus} GPUs of {gpu_kind} miss {target}: {what} at K={cfg.max_gpus} "
                f"({cfg.placement} placement, seeds {', '.join(map(str, seeds))}); the load model predicts ≥ {lower_bound} GPUs"
            )
        ]
    else:
        point = planner.points[(cfg.placement, answer)]
        per_seed = " / ".join(_pct(r.tier_starvation_pct("fast")) for r in point.runs)
        below = planner.points.get((cfg.placement, answer - 1))
        above = planner.points.get((cfg.placement, answer + 1))
        checks = []
        if below is not None:
            checks.append(f"K={answer - 1} misses (fast {_pc(below.fast_pct)}{planner.by_policy(below)})")
        if above is not None:
            checks.append(f"K={answer + 1} meets (fast {_pc(above.fast_pct)}{planner.by_policy(above)})")
        lines = [
            (
                f"this fleet needs {answer} GPUs of {gpu_kind} for {target}: expected fast {_pc(point.fast_pct)}, "
                f"slow {_pc(point.slow_pct)}{planner.by_policy(point)} (seeds {', '.join(map(str, seeds))}: fast {per_seed} %; worst GPU fast "
                f"{_pc(point.worst_fast_pct)}); predicted utilization mean {point.utilization_mean:.2f}, max "
                f"{point.utilization_max:.2f} ({cfg.placement} placement; load-model lower bound {lower_bound})"
            ),
        ]
        if checks:
            lines.append("verified: " + ", ".join(checks))
        dips = [k for k in planner.order if k < answer and planner.meets(planner.points[(cfg.placement, k)])]
        if dips:
            lines.append(
                f"note: K={', '.join(map(str, sorted(set(dips))))} met the target but a larger K did not (not monotone)"
            )
    lines.append(
        f"searched K (in order): {', '.join(map(str, planner.order))}; {wall:.1f} s wall, {cfg.duration_s:g} s simulated per GPU"
    )
    if split is not None:
        lines.append(split_line(answer, split))
    print("\n".join(lines))
    print()
    print(table(planner, answer))
    if cfg.figure:
        plot_plan(planner, answer, Path(cfg.figure), gpu_kind)
        print(f"wrote {cfg.figure}")
    if cfg.output:
        out = {
            "fleet": cfg.fleet,
            "fleet_description": fleet.describe(),
            "latency_profile": None if fleet.is_mixed else profile.name,
            "max_batch_size": None if fleet.is_mixed else fleet.max_batch_size,
            "policies": {
                p.name: {"latency_profile": p.profile().name, "max_batch_size": p.max_batch_size} for p in fleet.policies
            }
            if fleet.is_mixed
            else None,
            "scheduler": fleet.scheduler.label(),
            "placement": cfg.placement,
            "target_fast_pct": cfg.target_fast_pct,
            "target_slow_pct": cfg.target_slow_pct,
            "seeds": seeds,
            "duration_s": cfg.duration_s,
            "total_demand_gpus": demand,
            "lower_bound": lower_bound,
            "answer": answer,
            "searched": planner.order,
            "points": [p.record() for p in sorted(planner.points.values(), key=lambda p: (p.placement, p.gpus))],
            "answer_replicas": planner.points[(cfg.placement, answer)].runs[0].record()["replicas"]
            if answer is not None
            else None,
            "wall_s": wall,
            "split": split,
        }
        Path(cfg.output).parent.mkdir(parents=True, exist_ok=True)
        Path(cfg.output).write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {cfg.output}")
    return 0 if answer is not None or (split is not None and split["total"] is not None) else 1


def plan_split(fleet: Fleet, cfg: PlanConfig) -> dict[str, Any]:
    """A mixed fleet planned the other way: each policy's robots on GPUs of their own, searched as
    one-policy fleets with the same targets. Returns ``{"gpus": {policy: K or None}, "total": sum
    or None}``; progress goes to stderr."""
    gpus: dict[str, int | None] = {}
    for p in fleet.policies:
        alone = fleet.only(p.name)
        if not alone.robots:
            gpus[p.name] = 0
            continue
        planner = Planner(alone, cfg, quiet=True)
        gpus[p.name] = planner.search(max(1, math.ceil(alone.total_demand() - 1e-9)))
        print(f"[{PROG}] one set of GPUs per policy: {p.name}'s {alone.robots} robots alone need {gpus[p.name]} GPUs", file=sys.stderr)
    total = None if None in gpus.values() else sum(g or 0 for g in gpus.values())
    return {"gpus": gpus, "total": total}


def split_line(mixed: int | None, split: dict[str, Any]) -> str:
    """The comparison line: every GPU serving every policy against one set of GPUs per policy."""
    parts = " + ".join(f"{name} {k if k is not None else '?'}" for name, k in split["gpus"].items())
    total = split["total"]
    if mixed is None and total is None:
        verdict = "neither meets the target within --max_gpus"
    elif total is None or (mixed is not None and mixed <= total):
        verdict = "every GPU serving every policy needs " + ("as many" if mixed == total else "fewer")
    else:
        verdict = "one set of GPUs per policy needs fewer"
    return f"one set of GPUs per policy instead: {parts} = {total if total is not None else '?'} GPUs; {verdict}"


def gpu_description(fleet: Fleet) -> str:
    """What one GPU of the plan runs: its profile and cap, or every policy's when several share it."""
    if fleet.is_mixed:
        served = " + ".join(f"{p.name} {p.profile().name} b={p.max_batch_size}" for p in fleet.policies)
        return f"{served} ({fleet.scheduler.label()}, arbitrated)"
    return f"{fleet.profile().name} (b={fleet.max_batch_size}, {fleet.scheduler.label()})"


def table(planner: Planner, answer: int | None) -> str:
    """One row per K tried with the chosen placement (and the others' fast-tier starvation, if compared)."""
    cfg = planner.cfg
    others = [n for n in PLACEMENTS if n != cfg.placement and any(p == n for p, _ in planner.points)]
    header = f"{'K':>5} {'fast %':>8} {'slow %':>8} {'worst GPU fast %':>16} {'util mean/max':>13} {'robots/GPU':>10} {'target':>7}"
    header += "".join(f" {(p + ' fast %'):>14}" for p in planner.policies)
    header += "".join(f" {('fast% ' + n):>18}" for n in others)
    lines = [header, "-" * len(header)]
    for k in sorted(set(planner.order)):
        p = planner.points[(cfg.placement, k)]
        mark = "meets" if planner.meets(p) else "misses"
        if k == answer:
            mark += " <-"
        if p.placeable:
            spread = f"{min(p.runs[0].robots_per_replica)}-{max(p.runs[0].robots_per_replica)}"
            row = (
                f"{k:>5} {_pct(p.fast_pct, 8)} {_pct(p.slow_pct, 8)} {_pct(p.worst_fast_pct, 16)} "
                f"{p.utilization_mean:>6.2f}/{p.utilization_max:<6.2f} {spread:>10} {mark:>7}"
            ) + "".join(f" {_pct(p.policy_pct(name, 'fast'), 14)}" for name in planner.policies)
        else:
            row = f"{k:>5} {'-':>8} {'-':>8} {'-':>16} {'-':>13} {'full':>10} {mark:>7}" + f" {'-':>14}" * len(planner.policies)
        for n in others:
            q = planner.points.get((n, k))
            row += f" {_pct(q.fast_pct, 18)}" if q is not None and q.placeable else f" {'-':>18}"
        lines.append(row)
    return "\n".join(lines)


def plot_plan(planner: Planner, answer: int | None, path: Path, gpu_kind: str) -> None:
    """Fast and slow starvation vs K (each placement simulated), target lines, answer marked."""
    import matplotlib

    matplotlib.use("Agg")  # headless
    import matplotlib.pyplot as plt

    cfg = planner.cfg
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharex=True)
    names = [cfg.placement] + [n for n in PLACEMENTS if n != cfg.placement]
    markers = dict(zip(PLACEMENTS, ("v", "s", "^", "o"), strict=True))
    for name in names:
        pts = sorted((p for (n, _), p in planner.points.items() if n == name and p.placeable), key=lambda p: p.gpus)
        if not pts:
            continue
        # The chosen placement on top and solid; the others dashed, with their own markers, since
        # round_robin and least_loaded often coincide (with nobody leaving, both deal robots evenly).
        style = (
            {"lw": 2.0, "zorder": 3, "ms": 4}
            if name == cfg.placement
            else {"lw": 1.0, "alpha": 0.7, "ls": "--", "ms": 6, "mfc": "none"}
        )
        ks = [p.gpus for p in pts]
        for ax, values in ((axes[0], [p.fast_pct for p in pts]), (axes[1], [p.slow_pct for p in pts])):
            if not all(math.isnan(v) for v in values):
                ax.plot(ks, values, marker=markers.get(name, "o"), label=name, **style)
    axes[0].axhline(cfg.target_fast_pct, color="red", lw=1, ls=":", label=f"target {cfg.target_fast_pct:g} %")
    if cfg.target_slow_pct is not None:
        axes[1].axhline(cfg.target_slow_pct, color="red", lw=1, ls=":", label=f"target {cfg.target_slow_pct:g} %")
    if answer is not None:
        chosen = planner.points[(cfg.placement, answer)]
        for ax, y in ((axes[0], chosen.fast_pct), (axes[1], chosen.slow_pct)):
            ax.axvline(answer, color="green", lw=1, alpha=0.6)
            ax.plot([answer], [y], marker="*", ms=14, color="green", zorder=4, label=f"answer K={answer}")
    from matplotlib.ticker import MaxNLocator

    counts = planner.fleet.tier_counts()
    for ax, tier in zip(axes, ("fast", "slow"), strict=True):
        if not counts[tier]:
            ax.text(0.5, 0.5, "no robots of this tier", ha="center", va="center", transform=ax.transAxes, color="gray")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_title(f"{tier} tier ({counts[tier]} robots)", fontsize=9)
        ax.set_xlabel("GPUs K")
        ax.set_ylabel("starvation %")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(
        f"{planner.fleet.robots} robots on {gpu_kind}: starvation vs GPUs (mean of {cfg.seeds} seeds)", fontsize=10
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    """Console entry point: exit 0 with an answer, 1 if --max_gpus misses the target, 2 for bad input."""
    cfg = parse_or_exit(PlanConfig, argv, PROG)
    sys.exit(run_or_exit(run, cfg, PROG))


if __name__ == "__main__":
    main()
