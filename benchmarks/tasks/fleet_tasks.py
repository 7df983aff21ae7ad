"""The reference paper's experiment on real tasks: trained policies, a mixed MetaWorld fleet.

    python benchmarks/tasks/fleet_tasks.py --out=docs/results/tasks            # everything (~30 min)
    python benchmarks/tasks/fleet_tasks.py --parts=delay --out=docs/results/tasks
    python benchmarks/tasks/fleet_tasks.py --parts=horizon --out=/tmp/tasks    # the local part (~5 min)

Three parts, settings fixed before any run (h_min 10, h_max 20, 30 Hz, Lookahead weight 3 for the
dynamic tier, evaluation seeds from 1000; the checkpoints of examples/checkpoints):

- ``horizon``: each task's checkpoint in LeRobot's own loop (simulated time, no serving) with
  ``n_action_steps`` = 1, 5, 10, 20 actions executed per chunk, ``--episodes`` each: how much a
  long execution horizon costs the static and the dynamic task (the paper's second effect).
- ``delay``: the same loop made asynchronous as a served robot is (``--latency_ticks`` = 1..4: a
  chunk asked after 10 executed actions arrives that many ticks later; the arm executes the chunk
  it holds meanwhile and switches at the current index), no server: what a GPU's latency alone
  costs each task, the reference for the ``fleet`` part's served runs at the same delay.
- ``fleet``: the real server serving both checkpoints (``--policies``) to N MetaWorld robots,
  half on the dynamic task (``reach-moving``, fast tier), half on the static one (``push``, slow
  tier), each stepping its simulator at 30 Hz on the wall clock, under an emulated GPU latency
  profile (the paper's L40S π0.5; our H200 π0.5 graphs), for RR, EDF, Lookahead and Rollout (both
  w = 3 for the fast tier): success rate (Wilson 95 %), successes per minute and starvation per
  tier, per run. ``--append`` adds the runs to the ``fleet.json`` already in ``--out``.

Writes ``horizon.json`` and ``fleet.json`` (after every run) under ``--out`` and prints their tables; exits 1 if a
run fails. Figures come from one machine in one call; compare rows of one table only.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from lerobot_armory.bench.tasks import TasksConfig, run_local, run_served
from _checkpoints import CHECKPOINTS  # benchmarks/tasks/: the script's own directory

PROFILES = {"l40s-pi05": 5, "h200-pi05-graphs": 8}  # profile -> batch cap (the profile's longest batch)
SCHEDULERS = {"rr": 1.0, "edf": 1.0, "lookahead": 3.0, "rollout": 3.0}  # scheduler -> the fast tier's weight


def horizon_part(episodes: int) -> list[dict]:
    rows = []
    for task, path in CHECKPOINTS.items():
        for steps in (1, 5, 10, 20):
            cfg = TasksConfig(policy_path=str(path), task=task, mode="local", episodes=episodes, n_action_steps=steps)
            t0 = time.monotonic()
            r = run_local(cfg)
            rows.append({
                "task": task, "n_action_steps": steps, "episodes": r["episodes"], "successes": r["successes"],
                "success_rate": r["success_rate"], "interval95": list(r["interval95"]),
                "mean_ticks": sum(e["ticks"] for e in r["episode_results"]) / r["episodes"], "seconds": time.monotonic() - t0,
            })  # fmt: skip
            print(json.dumps(rows[-1]), flush=True)
    return rows


def delay_part(episodes: int) -> list[dict]:
    rows = []
    for task, path in CHECKPOINTS.items():
        for ticks in (0, 1, 2, 3, 4):
            cfg = TasksConfig(policy_path=str(path), task=task, mode="local", episodes=episodes, latency_ticks=ticks)
            r = run_local(cfg)
            rows.append({
                "task": task, "latency_ticks": ticks, "episodes": r["episodes"], "successes": r["successes"],
                "success_rate": r["success_rate"], "interval95": list(r["interval95"]),
                "mean_ticks": sum(e["ticks"] for e in r["episode_results"]) / r["episodes"],
            })  # fmt: skip
            print(json.dumps(rows[-1]), flush=True)
    return rows


def fleet_part(
    sizes: list[int], duration_s: float, profiles: list[str], schedulers: list[str], out: Path, append: bool = False
) -> list[dict]:
    base = TasksConfig(
        policy_path=",".join(f"{t}={p}" for t, p in CHECKPOINTS.items()), task="reach-moving,push", mode="served",
        episodes=0, duration_s=duration_s, groups=2,
    )  # fmt: skip
    work = Path(tempfile.mkdtemp(prefix="armory-fleet-tasks-"))
    rows, command = [], " ".join(sys.argv)
    if append and (out / "fleet.json").is_file():
        before = json.loads((out / "fleet.json").read_text())
        rows, command = before["rows"], f"{before['command']} ; then {command}"
    for n in sizes:
        for profile in profiles:
            for scheduler in schedulers:
                cfg = replace(
                    base, robots=n, emulate_profile=profile, max_batch_size=PROFILES[profile], scheduler=scheduler,
                    fast_weight=SCHEDULERS[scheduler], groups=min(2, n),
                )  # fmt: skip
                cfg.validate()
                r = run_served(cfg, work)
                row = {k: r[k] for k in ("robots", "scheduler", "emulate_profile", "episodes", "successes", "starvation_pct", "batch_sizes", "wall_s")}
                row["tiers"] = r["tiers"]
                row["per_robot"] = [
                    {k: s.get(k) for k in ("robot_id", "tier", "episodes_done", "successes", "successes_per_min", "starvation_pct")}
                    for s in r["per_robot"]
                ]
                rows.append(row)
                tiers = "; ".join(
                    f"{t}: {v['successes']}/{v['episodes']} {v['successes_per_min_per_robot']:.1f}/min starved {v['starvation_pct']:.1f}%"
                    for t, v in r["tiers"].items()
                )
                print(f"N={n} {profile} {scheduler}: {tiers}", flush=True)
                # Written after every run: a run that fails later keeps the ones before it.
                (out / "fleet.json").write_text(json.dumps({"command": command, "rows": rows}, indent=2) + "\n")
    return rows


def horizon_table(rows: list[dict]) -> str:
    lines = ["| task | actions executed per chunk | successes | rate [95 % interval] | mean ticks per episode |", "|---|---|---|---|---|"]
    for r in rows:
        lo, hi = r["interval95"]
        lines.append(
            f"| {r['task']} | {r['n_action_steps']} | {r['successes']}/{r['episodes']} | {r['success_rate']:.2f} [{lo:.2f}, {hi:.2f}] | {r['mean_ticks']:.0f} |"
        )
    return "\n".join(lines)


def delay_table(rows: list[dict]) -> str:
    lines = ["| task | delay (ticks at 30 Hz) | successes | rate [95 % interval] | mean ticks per episode |", "|---|---|---|---|---|"]
    for r in rows:
        lo, hi = r["interval95"]
        delay = "0 (LeRobot's synchronous loop)" if r["latency_ticks"] == 0 else str(r["latency_ticks"])
        lines.append(
            f"| {r['task']} | {delay} | {r['successes']}/{r['episodes']} | {r['success_rate']:.2f} [{lo:.2f}, {hi:.2f}] | {r['mean_ticks']:.0f} |"
        )
    return "\n".join(lines)


def fleet_table(rows: list[dict]) -> str:
    lines = [
        "| N | profile | scheduler | fast: successes | fast: rate [95 %] | fast: succ/min/robot | fast: starved % "
        "| slow: successes | slow: rate [95 %] | slow: succ/min/robot | slow: starved % | batches by size |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        cells = []
        for tier in ("fast", "slow"):
            v = r["tiers"].get(tier)
            if v is None:
                cells += ["–"] * 4
                continue
            lo, hi = v["interval95"]
            cells += [
                f"{v['successes']}/{v['episodes']}", f"{v['success_rate']:.2f} [{lo:.2f}, {hi:.2f}]",
                f"{v['successes_per_min_per_robot']:.1f}", f"{v['starvation_pct']:.1f}",
            ]  # fmt: skip
        sizes = ", ".join(f"{k}: {v}" for k, v in r["batch_sizes"].items())
        lines.append(f"| {r['robots']} | {r['emulate_profile']} | {r['scheduler']} | " + " | ".join(cells) + f" | {sizes} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", default="horizon,delay,fleet")
    ap.add_argument("--episodes", type=int, default=50, help="episodes per horizon setting")
    ap.add_argument("--robots", default="4,8")
    ap.add_argument("--duration_s", type=float, default=60.0)
    ap.add_argument("--profiles", default=",".join(PROFILES))
    ap.add_argument("--schedulers", default=",".join(SCHEDULERS))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--append", action="store_true", help="fleet: add the runs to OUT/fleet.json's rows")
    args = ap.parse_args()
    missing = [str(p) for p in CHECKPOINTS.values() if not (p / "config.json").is_file()]
    if missing:
        print(f"error: checkpoint(s) missing: {', '.join(missing)} (see examples/checkpoints/README.md)", file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    parts = set(args.parts.split(","))
    if "horizon" in parts:
        rows = horizon_part(args.episodes)
        (args.out / "horizon.json").write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows}, indent=2) + "\n")
        print(horizon_table(rows))
    if "delay" in parts:
        rows = delay_part(args.episodes)
        (args.out / "delay.json").write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows}, indent=2) + "\n")
        print(delay_table(rows))
    if "fleet" in parts:
        rows = fleet_part(
            [int(n) for n in args.robots.split(",")], args.duration_s, args.profiles.split(","), args.schedulers.split(","), args.out,
            args.append,
        )
        print(fleet_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
