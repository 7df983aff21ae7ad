"""GPUs for a mixed fleet: every GPU serving every policy, against one set of GPUs per policy.

For the mixed fleets of ``benchmarks/mixed_policies.py`` (libero timing, π0.5 on ``h100-pi05``
cap 5 and ACT on ``examples/profiles/act-h100.json`` cap 8; in each policy half the robots
fast-tier), at N robots, asks ``lerobot-armory-plan``'s search for the fewest GPUs meeting
fast-tier starvation ≤ ``--target_fast_pct``:

- **mixed**: every GPU serves both policies (each batch one policy's robots, the arbiter between
  them; placement charges each robot its own policy's cost); the target must hold for each
  policy's fast robots, as it must for each split fleet;
- **split**: each policy's robots planned as their own fleet, on GPUs that serve only that
  policy; the split answer is the sum of the two.

Prints one row per (fleet, N, scheduler) and exits 1 if a mixed plan needs more GPUs than the
split one (the claim of ``docs/results/multi_policy/README.md``), 0 otherwise.

    PYTHONPATH=. .venv/bin/python benchmarks/mixed_plan.py [--sizes=40,100,200] [--seeds=3]
        [--schedulers=edf,lookahead] [--output=docs/results/multi_policy/plan.json]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from mixed_policies import FLEETS, mixed_fleet  # noqa: E402

from lerobot_armory.sim.fleet_file import Fleet  # noqa: E402
from lerobot_armory.sim.plan import Planner, PlanConfig  # noqa: E402


def plan(fleet: Fleet, cfg: PlanConfig) -> tuple[int | None, float]:
    """(fewest GPUs meeting the target for every policy's robots, or None; the worst policy's
    fast-tier starvation % there)."""
    planner = Planner(fleet, cfg, quiet=True)
    with contextlib.redirect_stderr(io.StringIO()):
        answer = planner.search(max(1, math.ceil(fleet.total_demand() - 1e-9)))
    if not answer:
        return answer, math.nan
    point = planner.points[(cfg.placement, answer)]
    fast = max([point.fast_pct, *(point.policy_pct(p, "fast") for p in planner.policies)])
    return answer, fast


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="40,100,200")
    ap.add_argument("--schedulers", default="edf,lookahead")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--duration_s", type=float, default=30.0)
    ap.add_argument("--target_fast_pct", type=float, default=5.0)
    ap.add_argument("--output", default="")
    args = ap.parse_args()
    cfg = PlanConfig(target_fast_pct=args.target_fast_pct, seeds=args.seeds, duration_s=args.duration_s)
    rows, losses = [], []
    header = f"{'fleet':<11}{'N':>5} {'sched':<10}{'demand':>7} | {'mixed':>5} {'worst fast %':>12} | {'π0.5':>5} {'ACT':>4} {'split':>5} | {'saved':>5}"
    print(header + "\n" + "-" * len(header), flush=True)
    for name in FLEETS:
        for n in (int(x) for x in args.sizes.split(",")):
            for sched in args.schedulers.split(","):
                start = time.perf_counter()
                fleet = mixed_fleet(name, n, sched)
                k_mixed, fast = plan(fleet, cfg)
                k_alone = {p.name: plan(fleet.only(p.name), cfg)[0] for p in fleet.policies}
                k_split = None if None in k_alone.values() else sum(k_alone.values())  # type: ignore[arg-type]
                saved = None if k_mixed is None or k_split is None else k_split - k_mixed
                if saved is not None and saved < 0:
                    losses.append(f"{name} N={n} {sched}: mixed {k_mixed} > split {k_split}")
                rows.append({"fleet": name, "robots": n, "scheduler": sched, "demand_gpus": round(fleet.total_demand(), 3),
                             "mixed_gpus": k_mixed, "mixed_worst_policy_fast_pct": None if math.isnan(fast) else round(fast, 3),
                             "split_gpus": k_alone, "split_total": k_split, "saved": saved,
                             "wall_s": round(time.perf_counter() - start, 1)})  # fmt: skip
                print(
                    f"{name:<11}{n:>5} {sched:<10}{fleet.total_demand():>7.2f} | {k_mixed!s:>5} {fast:>12.2f} | "
                    f"{k_alone['pi05']!s:>5} {k_alone['act']!s:>4} {k_split!s:>5} | {saved!s:>5}",
                    flush=True,
                )
    if args.output:
        out = {"target_fast_pct": args.target_fast_pct, "seeds": args.seeds, "duration_s": args.duration_s,
               "placement": cfg.placement, "rows": rows}  # fmt: skip
        Path(args.output).write_text(json.dumps(out, indent=1) + "\n")
        print(f"wrote {args.output}")
    if losses:
        print("MISS: a mixed plan needs more GPUs than the split one: " + "; ".join(losses))
        return 1
    print("mixed needs no more GPUs than one set per policy in every row")
    return 0


if __name__ == "__main__":
    sys.exit(main())
