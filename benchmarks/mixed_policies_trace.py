"""One mixed-fleet run of ``mixed_policies.py`` seen batch by batch: how each policy used the device.

For one fleet, size and seed, each policy with its own scheduler type (``--schedulers=pi05=rollout,act=edf``
mixes types that arbitrate alike), prints per policy: starvation, batches and their mean size, device
seconds, and how often that policy's next batch started the moment its previous one ended (what a
scheduler planning as if the device were its own assumes) against the other policy's device time in
between otherwise. The diagnosis of Rollout across policies (docs/results/multi_policy/README.md) used it.

    PYTHONPATH=. .venv/bin/python benchmarks/mixed_policies_trace.py --fleet=act-heavy --robots=32 \\
        --seed=0 --duration_s=30 --schedulers=pi05=rollout,act=rollout
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from lerobot_armory.schedulers import make_scheduler_config
from lerobot_armory.sim.simulator import FleetSimulator

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mixed_policies import FLEETS, WARMUP_S, mixed_fleet  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fleet", default="act-heavy", choices=list(FLEETS))
    ap.add_argument("--robots", type=int, default=32)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration_s", type=float, default=30.0)
    ap.add_argument("--schedulers", default="pi05=rollout,act=rollout", help="policy=scheduler,...")
    args = ap.parse_args(argv)
    types = dict(item.split("=", 1) for item in args.schedulers.split(","))
    fleet = mixed_fleet(args.fleet, args.robots, "edf")
    schedulers = {p.name: make_scheduler_config(types[p.name]).make(p.profile(), p.max_batch_size) for p in fleet.policies}
    net = fleet.network()
    result = FleetSimulator(
        fleet.specs(), schedulers, args.duration_s, net, net, args.seed,
        warmup_s=WARMUP_S, policy_of=fleet.policy_of(), trace=True,
    ).run()  # fmt: skip
    batches = result.batches
    print(f"{args.fleet} N={args.robots} seed {args.seed}, {args.duration_s:g} s: all robots {result.avg_starvation_pct:.2f} % starved")
    for policy in schedulers:
        own = [i for i, b in enumerate(batches) if b.policy == policy]
        right_after, between = 0, []
        for a, c in zip(own, own[1:]):
            if batches[c].t_start - batches[a].t_done < 1e-9:
                right_after += 1
            else:
                between.append(sum(b.t_done - b.t_start for b in batches[a + 1 : c]))
        size = np.mean([len(batches[i].robot_ids) for i in own]) if own else 0.0
        print(
            f"  {policy:<5} {types[policy]:<9} starved {result.policy_starvation_pct(policy):5.2f} % | {len(own)} batches of "
            f"{size:.2f} robots, {result.device_s[policy]:.1f} device-s | next own batch right after: "
            f"{100 * right_after / max(1, len(own) - 1):.1f} %, else {1000 * np.mean(between) if between else 0:.1f} ms "
            "of the other policy's batches in between"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
