"""N = 10 scheduler comparison against EDF: horizon-free, weights fixed on training seeds.

``n10_paired.py`` sweeps fast-robot weights and reports every weight on the same seeds, so a
"win at some weight" is picked on the seeds it is scored on. Here the comparison is made honest:

- Steady state without a horizon: every run simulates ``--duration_s`` (120 s) and scores only the
  ticks after ``--warmup_s`` (20 s; ``SimConfig.warmup_s``). No scheduler is told any end.
- Every weighted setting is swept over the same fast-robot weight grid ``WEIGHTS``. EDF ignores
  weights: EDF (the baseline) and EDF with dispatch timing run at weight 1 only.
- Selection on training seeds (0 .. 11): for every (fleet, setting) the weight that maximises
  min(−Δfast, −Δslow) (the worse tier's improvement over EDF; Δ = setting − EDF starvation in
  points, mean over the paired seeds); ties go to the smaller weight.
- Evaluation on other seeds (1000 .. 1047): only the chosen weight runs, paired with EDF on the
  same seeds; each Δ is reported as mean ± 95 % half-width (normal approximation, ``interval``
  of ``n10_paired.py``). Verdict: "beats EDF on both tiers" only when both intervals lie below
  zero; "loses" when some tier's interval lies above zero; otherwise a tie or trade-off that is
  not significant.

Settings: Lookahead (depth 1), Rollout as registered, Rollout with the ``same`` base policy
(``rollout_same`` of ``armory_research.variants``), and the dispatch-timing variants (``wait_ms``
of every scheduler config): EDF and Rollout with ``wait_ms=10``. Fleets: libero and piper,
one-fast and half-fast (``FLEETS`` of ``n10_paired.py``).

Target (exits 1 on a miss), deliberately modest: the run completes and EDF +wait 10 ms does not
lose to EDF significantly on either tier in any fleet.

Run: ``.venv/bin/python research/benchmarks/n10_fixed.py [--train_seeds=12] [--eval_seeds=48]
[--eval_first_seed=1000] [--duration_s=120] [--warmup_s=20] [--out=FILE.md]``;
``--quick`` (2 training seeds, 4 evaluation seeds, 20 s, warm-up 5 s) is a smoke test.
"""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys
import time
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _study import Targets
from n10_paired import FLEETS, interval

from lerobot_armory.schedulers import make_scheduler_config
from lerobot_armory.sim.run import SimConfig, simulate

# research/ is on sys.path now (_study): register rollout_same (the package imports it too).
importlib.import_module("armory_research.variants")

WEIGHTS: tuple[float, ...] = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0)
WAIT_MS = 10.0
BASELINE = ("EDF", "edf", {}, (1.0,))
# (label, scheduler, options for make_scheduler_config, fast-robot weights swept on training seeds)
SETTINGS: list[tuple[str, str, dict[str, object], tuple[float, ...]]] = [
    ("lookahead", "lookahead", {"depth": 1}, WEIGHTS),
    ("rollout", "rollout", {}, WEIGHTS),
    ("rollout same", "rollout_same", {}, WEIGHTS),
    (f"EDF +wait {WAIT_MS:g} ms", "edf", {"wait_ms": WAIT_MS}, (1.0,)),  # EDF ignores weights
    (f"rollout +wait {WAIT_MS:g} ms", "rollout", {"wait_ms": WAIT_MS}, WEIGHTS),
]
CHECKED = SETTINGS[3][0]  # the target's setting: EDF with dispatch timing
SCRIPT = "research/benchmarks/n10_fixed.py"

Job = tuple[str, str, str, dict[str, object], float, int, float, float]


def run_one(job: Job) -> tuple[float, float, float, float, float]:
    """(fast %, slow %, decision CPU p99 ms, decision wall p99 ms, held s) of one seed."""
    preset, mix, name, options, weight, seed, duration, warmup = job
    cfg = SimConfig(
        preset=preset, mix=mix, robots=10, scheduler=make_scheduler_config(name, **options),
        fast_weight=weight, duration_s=duration, warmup_s=warmup,
    ).resolved()  # fmt: skip
    r = simulate(cfg, seed)
    tiers = r["tiers"]
    return (
        tiers["fast"]["starvation_pct"], tiers["slow"]["starvation_pct"],
        r["decision_cpu_ms_p99"], r["decision_ms_p99"], r["held_s"],
    )  # fmt: skip


def select_weight(edf: np.ndarray, runs: dict[float, np.ndarray]) -> tuple[float, float, float]:
    """(weight, Δfast, Δslow): the weight maximising min(−Δfast, −Δslow); ties → smaller weight."""
    best: tuple[float, float, float] | None = None
    best_score = -np.inf
    for w in sorted(runs):
        r = runs[w]
        df, ds = float((r[:, 0] - edf[:, 0]).mean()), float((r[:, 1] - edf[:, 1]).mean())
        score = min(-df, -ds)
        if score > best_score + 1e-9:
            best, best_score = (w, df, ds), score
    assert best is not None
    return best


def verdict(df: float, hf: float, ds: float, hs: float) -> str:
    if df + hf < 0 and ds + hs < 0:
        return "beats EDF on both tiers"
    worse = [tier for tier, d, h in (("fast", df, hf), ("slow", ds, hs)) if d - h > 0]
    if worse:
        return f"loses ({' and '.join(worse)} tier{'s' if len(worse) > 1 else ''})"
    return "tie/trade-off (not significant)"


def git_commit() -> str:
    try:
        root = Path(__file__).resolve().parents[2]
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", "lerobot_armory", "research", "benchmarks"],
            cwd=root, capture_output=True, text=True, check=True,
        ).stdout.split("\n")  # fmt: skip
        dirty = [line[3:] for line in dirty if line.strip()]
        return head + (f" (uncommitted changes to {', '.join(sorted(dirty))})" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


class Phases:
    """Submits one phase's jobs (a fleet and a setting, all weights and seeds) and collects them
    in submission order, printing a progress line as each phase completes."""

    def __init__(self, pool: ProcessPoolExecutor, start: float) -> None:
        self.pool, self.start = pool, start
        self.queue: list[tuple[str, list[tuple[tuple, list[Future]]]]] = []

    def submit(self, title: str, groups: dict[tuple, list[Job]]) -> None:
        self.queue.append(
            (title, [(key, [self.pool.submit(run_one, j) for j in jobs]) for key, jobs in groups.items()])
        )

    def collect(self) -> dict[tuple, np.ndarray]:
        out: dict[tuple, np.ndarray] = {}
        total = sum(len(fs) for _, groups in self.queue for _, fs in groups)
        done = 0
        for title, groups in self.queue:
            for key, futures in groups:
                out[key] = np.array([f.result() for f in futures])
                done += len(futures)
            elapsed = time.perf_counter() - self.start
            print(f"[{elapsed:7.0f} s] {title}: done ({done}/{total} runs of this stage)", file=sys.stderr, flush=True)
        self.queue = []
        return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--train_seeds", type=int, default=None, help="training seeds train_first_seed .. (default 12)")
    ap.add_argument("--train_first_seed", type=int, default=0)
    ap.add_argument("--eval_seeds", type=int, default=None, help="evaluation seeds eval_first_seed .. (default 48)")
    ap.add_argument("--eval_first_seed", type=int, default=1000)
    ap.add_argument("--duration_s", type=float, default=None, help="simulated seconds per run (default 120)")
    ap.add_argument("--warmup_s", type=float, default=None, help="first seconds not scored (default 20)")
    ap.add_argument("--workers", type=int, default=2, help="worker processes")
    ap.add_argument(
        "--quick", action="store_true", help="smoke test: 2 training seeds, 4 evaluation seeds, 20 s, warm-up 5 s"
    )
    ap.add_argument("--out", help="also write the tables to this markdown file")
    args = ap.parse_args()
    defaults = (2, 4, 20.0, 5.0) if args.quick else (12, 48, 120.0, 20.0)
    for attr, value in zip(("train_seeds", "eval_seeds", "duration_s", "warmup_s"), defaults, strict=True):
        if getattr(args, attr) is None:
            setattr(args, attr, value)
    train = list(range(args.train_first_seed, args.train_first_seed + args.train_seeds))
    evals = list(range(args.eval_first_seed, args.eval_first_seed + args.eval_seeds))
    if set(train) & set(evals):
        sys.exit("training and evaluation seeds overlap")
    if args.train_seeds < 1 or args.eval_seeds < 2:
        sys.exit("need >= 1 training seed and >= 2 evaluation seeds")
    D, W = args.duration_s, args.warmup_s

    def jobs(preset: str, mix: str, name: str, opts: dict[str, object], w: float, seeds: list[int]) -> list[Job]:
        return [(preset, mix, name, opts, w, s, D, W) for s in seeds]

    start = time.perf_counter()
    commit = git_commit()  # the code the workers import now (recorded again at the end)
    n_train = len(FLEETS) * (1 + sum(len(ws) for *_, ws in SETTINGS)) * len(train)
    n_eval = len(FLEETS) * (1 + len(SETTINGS)) * len(evals)
    print(
        f"training: {n_train} runs on seeds {train[0]}..{train[-1]}; evaluation: {n_eval} runs on seeds "
        f"{evals[0]}..{evals[-1]}; {D:g} s each, warm-up {W:g} s, {args.workers} workers",
        file=sys.stderr, flush=True,
    )  # fmt: skip
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        # Stage 1: training seeds, every weight of the grid.
        phases = Phases(pool, start)
        for preset, mix in FLEETS:
            for label, name, opts, weights in [BASELINE, *SETTINGS]:
                phases.submit(
                    f"train {preset} {mix}: {label} ({len(weights)} weight(s) x {len(train)} seeds)",
                    {(preset, mix, label, w): jobs(preset, mix, name, opts, w, train) for w in weights},
                )
        train_runs = phases.collect()
        chosen: dict[tuple[str, str, str], tuple[float, float, float]] = {}
        for preset, mix in FLEETS:
            edf = train_runs[(preset, mix, "EDF", 1.0)]
            for label, _, _, weights in SETTINGS:
                chosen[(preset, mix, label)] = select_weight(
                    edf, {w: train_runs[(preset, mix, label, w)] for w in weights}
                )
        per_run = (time.perf_counter() - start) * args.workers / n_train
        print(
            f"weights fixed; evaluation estimated at ~{per_run * n_eval / args.workers / 60:.1f} min",
            file=sys.stderr,
            flush=True,
        )
        # Stage 2: evaluation seeds, only the chosen weight, paired with EDF.
        for preset, mix in FLEETS:
            phases.submit(f"eval {preset} {mix}: EDF", {(preset, mix, "EDF"): jobs(preset, mix, "edf", {}, 1.0, evals)})
            for label, name, opts, _ in SETTINGS:
                w = chosen[(preset, mix, label)][0]
                phases.submit(
                    f"eval {preset} {mix}: {label} w={w:g}",
                    {(preset, mix, label): jobs(preset, mix, name, opts, w, evals)},
                )
        eval_runs = phases.collect()
    wall = time.perf_counter() - start

    targets = Targets()
    cmd = (
        f".venv/bin/python {SCRIPT} --train_seeds={args.train_seeds} --train_first_seed={args.train_first_seed} "
        f"--eval_seeds={args.eval_seeds} --eval_first_seed={args.eval_first_seed} --duration_s={D:g} --warmup_s={W:g}"
        + (f" --out={args.out}" if args.out else "")
    )
    md = [
        "Protocol:\n",
        (
            f"- Horizon-free steady state: N = 10, each run simulates {D:g} s and scores only the ticks after a "
            f"{W:g} s warm-up (`SimConfig(robots=10, duration_s={D:g}, warmup_s={W:g})`); no scheduler is told any end."
        ),
        (
            f"- Fast-robot weight grid, the same for every weighted setting: {', '.join(f'{w:g}' for w in WEIGHTS)}. "
            "EDF ignores weights: EDF (the baseline, `wait_ms=0`) and EDF +wait run at weight 1 only."
        ),
        (
            f"- Selection on training seeds {train[0]}..{train[-1]} ({len(train)} seeds): per (fleet, setting), the weight "
            "maximising min(−Δfast, −Δslow), Δ = setting − EDF starvation (points), mean over the paired seeds; ties → smaller weight."
        ),
        (
            f"- Evaluation on seeds {evals[0]}..{evals[-1]} ({len(evals)} seeds), never looked at during selection: only the "
            "chosen weight runs, paired with EDF on the same seeds. Δ = mean of the per-seed differences ± 95 % half-width "
            "(1.96 standard errors)."
        ),
        (
            "- Verdict: *beats EDF on both tiers* only when both tiers' intervals lie below zero (mean + half < 0); "
            "*loses* when some tier's interval lies above zero (mean − half > 0); otherwise *tie/trade-off (not significant)*."
        ),
        (
            f"- Decision time: p99 of the decision CPU time / p99 of its wall time, ms, the max over the evaluation seeds. "
            f"Held: for the `wait_ms={WAIT_MS:g}` variants, the device time spent waiting on purpose (`held_s`, whole run "
            f"including warm-up), mean per run, as % of the {D:g} s duration."
        ),
        (
            f"- Settings: lookahead (depth 1), rollout, rollout same (`rollout_same`, `armory_research.variants`), "
            f"EDF +wait {WAIT_MS:g} ms (`edf`, `wait_ms={WAIT_MS:g}`), rollout +wait {WAIT_MS:g} ms (`rollout`, `wait_ms={WAIT_MS:g}`)."
        ),
        f"- Code at commit {commit}"
        + (
            ""
            if git_commit() == commit
            else f" at the start, {git_commit()} at the end (the tree changed during the run)"
        )
        + f"; wall time {wall / 60:.1f} min with {args.workers} worker processes.",
        f"\nReproduce: `{cmd}`\n",
    ]
    if args.quick:
        md.insert(0, "**Smoke test (`--quick`): too few seeds for any conclusion.**\n")
    loses: list[str] = []
    for preset, mix in FLEETS:
        edf = eval_runs[(preset, mix, "EDF")]
        md += [
            f"\n**{preset}, {mix}, N=10**\n",
            "| setting | weight | train Δfast | train Δslow | fast % | slow % | Δfast | Δslow | verdict | decision p99 cpu / wall ms | held % |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
            (
                f"| EDF (baseline) | – | – | – | {edf[:, 0].mean():.2f} | {edf[:, 1].mean():.2f} | – | – | – | "
                f"{edf[:, 2].max():.3f} / {edf[:, 3].max():.3f} | – |"
            ),
        ]
        for label, _, opts, _ in SETTINGS:
            w, tf, ts = chosen[(preset, mix, label)]
            r = eval_runs[(preset, mix, label)]
            (df, hf), (ds, hs) = interval(r[:, 0] - edf[:, 0]), interval(r[:, 1] - edf[:, 1])
            v = verdict(df, hf, ds, hs)
            held = f"{100 * r[:, 4].mean() / D:.2f}" if opts.get("wait_ms") else "–"
            md.append(
                f"| {label} | {w:g} | {tf:+.2f} | {ts:+.2f} | {r[:, 0].mean():.2f} | {r[:, 1].mean():.2f} | "
                f"{df:+.2f} ± {hf:.2f} | {ds:+.2f} ± {hs:.2f} | {v} | {r[:, 2].max():.3f} / {r[:, 3].max():.3f} | {held} |"
            )
            if label == CHECKED and v.startswith("loses"):
                loses.append(f"{preset} {mix}: {v}")
    md.append("\n**Training sweep** (Δfast / Δslow vs EDF, mean over the training seeds; * = chosen):\n")
    md += ["| fleet | setting | " + " | ".join(f"w={w:g}" for w in WEIGHTS) + " |", "|---|---|" + "---|" * len(WEIGHTS)]
    for preset, mix in FLEETS:
        edf = train_runs[(preset, mix, "EDF", 1.0)]
        for label, _, _, weights in SETTINGS:
            cells = []
            for w in WEIGHTS:
                if w not in weights:
                    cells.append("")
                    continue
                r = train_runs[(preset, mix, label, w)]
                star = "*" if chosen[(preset, mix, label)][0] == w else ""
                cells.append(f"{(r[:, 0] - edf[:, 0]).mean():+.2f} / {(r[:, 1] - edf[:, 1]).mean():+.2f}{star}")
            md.append(f"| {preset} {mix} | {label} | " + " | ".join(cells) + " |")
    md.append(
        f"\nTarget: the run completed and {CHECKED} does not lose to EDF significantly on either tier in any fleet: "
        + ("met." if not loses else "**missed**: " + "; ".join(loses) + ".")
    )
    text = "\n".join(md) + "\n"
    print(text)
    if loses:
        print(f"{CHECKED} loses to EDF significantly in: " + "; ".join(loses))
    targets.check(f"fleets where {CHECKED} loses to EDF significantly on some tier", float(len(loses)), 0.0, "fleets")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text("# N = 10 against EDF: steady state, weights fixed on training seeds\n\n" + text)
        print(f"wrote {args.out}")
    print(f"wall time {wall:.0f} s")
    targets.finish()


if __name__ == "__main__":
    main()
