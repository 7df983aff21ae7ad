"""Several policies on one device vs one server per policy with the device time divided.

For mixed fleets at the libero preset's timing (fps 20, H 10, h_min 1; in each policy half the
robots on the fast tier, h_max 6 and weight 3, half on the slow tier, h_max 10), simulates

- **mixed**: the whole fleet on ONE device, each policy's batches arbitrated by
  :class:`~lerobot_armory.arbiter.PolicyArbiter` (each batch one policy's robots, that policy's
  ``d_infer(b)``);
- **split**: two servers, one per policy, each on a fixed share of the device: its ``d_infer(b)``
  divided by the share (time slicing, the scheduler told so). Two split rules, fixed before any
  result was seen: ``even`` (0.5 / 0.5) and ``demand`` (each policy's share proportional to its
  robots' predicted device demand, the placement load model of ``lerobot_armory.placement`` on a
  whole device).

Profiles (fixed before any result was seen): the slow policy is π0.5 on an H100 (built-in
``h100-pi05``, 42-87 ms for b = 1..5, cap 5, its measured sizes); the fast policy is ACT on the same
H100 kind (``examples/profiles/act-h100.json``: the measured engine ms for b = 2..8, 8.6-10.0 ms,
rounded up to a flat 10 ms; cap 8, its measured sizes). Both were measured on one device kind, so
"one device" is the same device for both; the H200 π0.5 profile has no ACT counterpart.

Prints a table (fleet, N, predicted demand, scheduler; ACT ("fast policy") and π0.5 ("slow
policy") starvation, mixed vs each split) and writes ``docs/results/multi_policy/sim.json``. Exits
non-zero only on an error: a loss of the mixed device is a result, reported in the table.

    PYTHONPATH=. .venv/bin/python benchmarks/mixed_policies.py [--duration_s=60] [--seeds=3]
        [--schedulers=edf,lookahead,rr,rollout] [--sizes=16,24,32] [--output=PATH]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.schedulers import make_scheduler_config
from lerobot_armory.sim.fleet_file import Fleet, PolicySpec, fleet_from_dict
from lerobot_armory.sim.run import fleet_simulator
from lerobot_armory.sim.simulator import FleetSimulator, SimResult

ROOT = Path(__file__).resolve().parents[1]
SLOW = PolicySpec("pi05", "h100-pi05", 5)
FAST = PolicySpec("act", str(ROOT / "examples" / "profiles" / "act-h100.json"), 8)
TIMING = {"fps": 20, "chunk_size": 10, "h_min": 1}
# Fleet name -> fraction of the robots on the slow policy (π0.5); the rest run ACT.
FLEETS = {"half": 0.5, "pi05-heavy": 0.75, "act-heavy": 0.25}
SPLITS = ("even", "demand")
WARMUP_S = 5.0


def mixed_fleet(name: str, n: int, scheduler: str) -> Fleet:
    """``n`` robots, ``FLEETS[name]`` of them on π0.5, each policy's half-fast / half-slow."""
    n_slow = round(n * FLEETS[name])
    groups = []
    for policy, count in ((SLOW.name, n_slow), (FAST.name, n - n_slow)):
        fast = count // 2
        for tier, k, h_max, weight in (("fast", fast, 6, 3), ("slow", count - fast, 10, 1)):
            if k:
                groups.append(
                    {"name": f"{policy}-{tier}", "count": k, "h_max": h_max, "weight": weight, "tier": tier,
                     "policy": policy, **TIMING}
                )  # fmt: skip
    data = {
        "scheduler": scheduler,
        "policies": {
            p.name: {"latency_profile": p.latency_profile, "max_batch_size": p.max_batch_size} for p in (SLOW, FAST)
        },
        "robots": groups,
    }
    return fleet_from_dict(data, f"{name}-{n}")


def policy_demand(fleet: Fleet) -> dict[str, float]:
    """Each policy's predicted device demand on a whole device (the placement load model)."""
    out = {}
    for p in fleet.policies:
        groups = tuple(g for g in fleet.groups if g.policy == p.name)
        alone = Fleet(
            groups, p.latency_profile, p.max_batch_size, fleet.scheduler, fleet.net_median_ms, fleet.net_sigma
        )
        out[p.name] = alone.total_demand() if groups else 0.0
    return out


def shares(rule: str, demand: dict[str, float]) -> dict[str, float]:
    """The device share of each policy's server under ``rule`` (``even`` or ``demand``)."""
    if rule == "even":
        return dict.fromkeys(demand, 1.0 / len(demand))
    total = sum(demand.values())
    return {name: d / total for name, d in demand.items()}


def split_run(fleet: Fleet, share: dict[str, float], duration_s: float, seed: int) -> dict[str, SimResult]:
    """One server per policy, its ``d_infer(b)`` divided by its share of the device."""
    out = {}
    for p in fleet.policies:
        specs = [s for g in fleet.groups if g.policy == p.name for s in g.specs()]
        base = p.profile()
        sliced = LatencyProfile(f"{base.name}/{share[p.name]:.3f}", tuple(ms / share[p.name] for ms in base.latency_ms))
        scheduler = fleet.scheduler.make(sliced, p.max_batch_size)
        net = fleet.network()
        out[p.name] = FleetSimulator(specs, scheduler, duration_s, net, net, seed, warmup_s=WARMUP_S).run()
    return out


def starvation(results: dict[str, SimResult] | SimResult, policy: str) -> float:
    """Mean starvation % of ``policy``'s robots (in the mixed run or its own split server)."""
    if isinstance(results, SimResult):
        return results.policy_starvation_pct(policy)
    return results[policy].avg_starvation_pct


def run_point(name: str, n: int, scheduler: str, duration_s: float, seeds: int, first_seed: int = 0) -> dict[str, Any]:
    """Mixed vs every split rule for one fleet, size and scheduler, over ``seeds`` seeds."""
    fleet = mixed_fleet(name, n, scheduler)
    demand = policy_demand(fleet)
    arms: dict[str, dict[str, list[float]]] = {arm: {"act": [], "pi05": [], "all": []} for arm in ("mixed", *SPLITS)}
    start = time.perf_counter()
    counts = fleet.policy_counts()
    for seed in range(first_seed, first_seed + seeds):
        mixed = fleet_simulator(fleet, duration_s, seed, warmup_s=WARMUP_S).run()
        _add(arms["mixed"], mixed, counts)
        for rule in SPLITS:
            _add(arms[rule], split_run(fleet, shares(rule, demand), duration_s, seed), counts)
    return {
        "fleet": name,
        "robots": n,
        "policy_robots": counts,
        "scheduler": scheduler,
        "demand": demand,
        "shares": {rule: shares(rule, demand) for rule in SPLITS},
        "seeds": seeds,
        "first_seed": first_seed,
        "duration_s": duration_s,
        "warmup_s": WARMUP_S,
        "starvation_pct": {arm: {k: v for k, v in vals.items()} for arm, vals in arms.items()},
        "wall_s": time.perf_counter() - start,
    }


def _add(arm: dict[str, list[float]], results: dict[str, SimResult] | SimResult, counts: dict[str, int]) -> None:
    per = {p: starvation(results, p) for p in counts}
    arm["act"].append(per["act"])
    arm["pi05"].append(per["pi05"])
    # the whole fleet's mean over robots, weighting each policy's mean by its robot count
    arm["all"].append(sum(per[p] * c for p, c in counts.items()) / sum(counts.values()))


def table(points: list[dict[str, Any]]) -> str:
    """One row per (fleet, N, scheduler): mean starvation % over seeds, mixed vs each split."""
    header = (
        f"{'fleet':<10} {'N':>3} {'demand':>6} {'sched':<9} | {'ACT mixed':>9} {'even':>6} {'demand':>6} | "
        f"{'π0.5 mixed':>10} {'even':>6} {'demand':>6} | {'all mixed':>9} {'even':>6} {'demand':>6} | "
        f"{'mixed best?':<11}"
    )
    lines = [header, "-" * len(header)]
    for p in points:
        s = p["starvation_pct"]

        def m(arm: str, key: str) -> float:
            return float(np.mean(s[arm][key]))

        best = min(m(rule, "all") for rule in SPLITS)
        verdict = "yes" if m("mixed", "all") < best - 0.05 else ("tie" if m("mixed", "all") <= best + 0.05 else "NO")
        lines.append(
            f"{p['fleet']:<10} {p['robots']:>3} {sum(p['demand'].values()):>6.2f} {p['scheduler']:<9} | "
            f"{m('mixed', 'act'):>9.2f} {m('even', 'act'):>6.2f} {m('demand', 'act'):>6.2f} | "
            f"{m('mixed', 'pi05'):>10.2f} {m('even', 'pi05'):>6.2f} {m('demand', 'pi05'):>6.2f} | "
            f"{m('mixed', 'all'):>9.2f} {m('even', 'all'):>6.2f} {m('demand', 'all'):>6.2f} | {verdict:<11}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Run every point, print the table, write the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration_s", type=float, default=60.0)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first_seed", type=int, default=0, help="held-out checks: seeds first_seed.. (the study used 0..2)")
    ap.add_argument("--schedulers", default="edf,lookahead,rr,rollout")
    ap.add_argument("--fleets", default=",".join(FLEETS))
    ap.add_argument("--sizes", default="16,24,32")
    ap.add_argument("--output", default=str(ROOT / "docs" / "results" / "multi_policy" / "sim.json"))
    args = ap.parse_args(argv)
    if not args.duration_s > WARMUP_S or args.seeds < 1:
        ap.error(f"--duration_s must exceed the {WARMUP_S:g} s warm-up and --seeds be >= 1")
    for name in args.schedulers.split(","):
        make_scheduler_config(name)  # an unknown scheduler fails before hours of simulation
    points = []
    for name in args.fleets.split(","):
        for n in (int(x) for x in args.sizes.split(",")):
            for scheduler in args.schedulers.split(","):
                point = run_point(name, n, scheduler, args.duration_s, args.seeds, args.first_seed)
                points.append(point)
                print(f"{name} N={n} {scheduler}: {point['wall_s']:.1f} s", file=sys.stderr, flush=True)
    print(table(points))
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    given = argv if argv is not None else sys.argv[1:]
    command = "PYTHONPATH=. .venv/bin/python benchmarks/mixed_policies.py " + " ".join(given)
    out.write_text(json.dumps({"command": command.strip(), "points": points}, indent=2) + "\n")
    print(f"wrote {len(points)} points to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
