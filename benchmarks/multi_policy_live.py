"""Two policies on one device, live: one server serving both (``--policies``) against two servers,
one per policy, each given part of the device.

The fleet (fixed before any run): libero timing (H = 10, 20 fps, h_min 1, h_max 6 fast / 10 slow),
``--robots_per_policy`` robots per policy, half of each fast (weight 3). Policy ``pi05`` takes the
L40S π0.5 profile (73 / 110 / 142 ms at b = 1..3), policy ``act`` ACT's H100 figure (13.8 ms
at b = 1..3, docs/results/gpu); cap 3 each. Both run the tiny random ACT on the CPU, padded to
their profile (``EmulatedLatencyEngine``): the device time is the profile's, whatever this
machine does.

- *mixed*: one server, both policies, one device: each batch holds one policy's robots, the
  arbiter picks whose batch runs next.
- *split, even*: two servers, each with half the device (its profile ×2: a batch takes twice as
  long when the device runs two servers' batches interleaved).
- *split, by demand*: two servers, the device divided in proportion to each policy's demand
  (robots' chunks per second × d_infer(cap) / cap), computed from the fleet and the profiles.

Robots run the real client loop (``ArmoryClient``) in threads of this process over loopback
gRPC; starvation per policy and tier is what they report. Prints the table, writes JSON, exits 1
only on an error (a loss is a finding, reported as such).

    .venv/bin/python benchmarks/multi_policy_live.py --duration_s=30 --out=docs/results/multi_policy/live.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np

FPS, H, H_MIN, H_FAST, H_SLOW, CAP, FAST_WEIGHT = 20.0, 10, 1, 6, 10, 3, 3.0
PROFILES_MS = {"pi05": (73.0, 109.8, 142.4), "act": (13.8, 13.8, 13.8)}
SCHEDULERS = ("edf", "lookahead")


def demand_share(robots_per_policy: int) -> dict[str, float]:
    """Each policy's share of device time its robots need, at full batches: chunks/s × d_infer(cap)/cap."""
    fast = robots_per_policy // 2
    chunks_s = fast * FPS / H_FAST + (robots_per_policy - fast) * FPS / H_SLOW
    need = {name: chunks_s * ms[CAP - 1] / 1000.0 / CAP for name, ms in PROFILES_MS.items()}
    total = sum(need.values())
    return {name: n / total for name, n in need.items()}


def engine_for(path: str, profile_ms: tuple[float, ...], name: str) -> tuple[Any, Any, Any]:
    """(the engine the loop runs: the tiny ACT padded to the profile, its PolicyInfo, the profile)."""
    from lerobot_armory.engine.emulation import EmulatedLatencyEngine
    from lerobot_armory.engine.options import PolicyOptions
    from lerobot_armory.engine.policy_engine import PolicyEngine
    from lerobot_armory.entrypoints.grpc.service import PolicyInfo
    from lerobot_armory.inference_latency import LatencyProfile

    engine = PolicyEngine(PolicyOptions(path, "cpu", cpu_threads=1))
    engine.warmup(CAP, log_progress=False)
    profile = LatencyProfile(name, profile_ms)
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    return EmulatedLatencyEngine(engine, profile), info, profile


def fleet_policy() -> Any:
    """Grants the fast robots their weight of 3 (the built-in policy caps every weight at 1)."""
    from lerobot_armory.serving.fleet_policy import FleetPolicy

    return FleetPolicy.from_dict({"default": {"max_weight": FAST_WEIGHT}}, "multi_policy_live")


def scheduler_config(name: str) -> Any:
    from lerobot_armory.schedulers import EarliestDeadlineConfig, LookaheadConfig

    return {"edf": EarliestDeadlineConfig(), "lookahead": LookaheadConfig()}[name]


def run_fleet(addresses: dict[str, str], features: dict[str, Any], robots_per_policy: int, duration_s: float, named: bool) -> list[dict]:
    """Every robot's stats after ``duration_s`` (``addresses``: policy -> server address)."""
    from lerobot_armory.robot.client import ArmoryClient, Backoff, RobotIdentity

    rng = np.random.default_rng(0)
    obs = {n: (rng.integers(0, 255, s, dtype=np.uint8) if d == "uint8" else rng.standard_normal(s).astype(d)) for n, (d, s) in features.items()}
    clients = []
    for policy, address in addresses.items():
        for k in range(robots_per_policy):
            fast = k < robots_per_policy // 2
            ident = RobotIdentity(
                f"{policy}-{k}", FPS, H_MIN, H_FAST if fast else H_SLOW, FAST_WEIGHT if fast else 1.0,
                "fast" if fast else "slow", "", policy if named else "",
            )  # fmt: skip
            clients.append((policy, ArmoryClient(address, ident, features, observe=lambda: obs, act=lambda a: None, backoff=Backoff(0.2, 1.0, 20.0))))
    results: list[dict] = []
    lock = threading.Lock()

    def one(policy: str, client: Any) -> None:
        stats = client.run(duration_s)
        client.close()
        with lock:
            results.append({**stats, "policy": policy})

    threads = [threading.Thread(target=one, args=pc) for pc in clients]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


def summarise(stats: list[dict]) -> dict[str, float]:
    out = {}
    for policy in PROFILES_MS:
        for tier in ("fast", "slow"):
            rows = [s["starvation_pct"] for s in stats if s["policy"] == policy and s["tier"] == tier]
            out[f"{policy}/{tier}"] = round(statistics.mean(rows), 2) if rows else float("nan")
    out["all"] = round(statistics.mean(s["starvation_pct"] for s in stats), 2)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--robots_per_policy", type=int, default=6)
    p.add_argument("--duration_s", type=float, default=30.0)
    p.add_argument("--schedulers", default="edf,lookahead")
    p.add_argument("--out", default=None, help="write the results as JSON here")
    args = p.parse_args()

    from lerobot_armory.entrypoints.server import ArmoryServer, ExtraPolicy, tune_process
    from lerobot_armory.policies.demo.build import DemoPolicyConfig, make_demo_policy

    tune_process()
    work = Path(tempfile.mkdtemp(prefix="armory-multi-policy-"))
    paths = {}
    for k, name in enumerate(PROFILES_MS):
        paths[name] = str(work / name)
        make_demo_policy(DemoPolicyConfig(output=paths[name], chunk_size=H, state_dim=2, cameras="front", image_size=32, dim_model=32, n_encoder_layers=1, seed=k))
    shares = demand_share(args.robots_per_policy)
    setups = {"mixed": None, "split-even": {n: 0.5 for n in PROFILES_MS}, "split-demand": shares}
    print(
        f"{2 * args.robots_per_policy} robots (libero timing, half fast), policies {', '.join(PROFILES_MS)}; "
        f"demand shares {', '.join(f'{n} {s:.2f}' for n, s in shares.items())}; {args.duration_s:g} s per run",
        flush=True,
    )
    rows = []
    for sched in [s.strip() for s in args.schedulers.split(",") if s.strip()]:
        for setup, split in setups.items():
            servers = []
            try:
                if split is None:
                    (e1, i1, p1), (e2, i2, p2) = (engine_for(paths[n], PROFILES_MS[n], n) for n in PROFILES_MS)
                    names = list(PROFILES_MS)
                    server = ArmoryServer(
                        e1, i1, p1, scheduler_config(sched), CAP, port=0, fleet_policy=fleet_policy(), policy_name=names[0],
                        others=(ExtraPolicy(names[1], e2, i2, p2, CAP),),
                    ).start()  # fmt: skip
                    servers.append(server)
                    addresses = {n: server.address for n in names}
                    features = {f.name: (f.dtype, f.shape) for f in i1.wire_features}
                else:
                    addresses = {}
                    for name in PROFILES_MS:
                        scaled = tuple(ms / split[name] for ms in PROFILES_MS[name])
                        engine, info, profile = engine_for(paths[name], scaled, name)
                        server = ArmoryServer(engine, info, profile, scheduler_config(sched), CAP, port=0, fleet_policy=fleet_policy()).start()
                        servers.append(server)
                        addresses[name] = server.address
                        features = {f.name: (f.dtype, f.shape) for f in info.wire_features}
                stats = run_fleet(addresses, features, args.robots_per_policy, args.duration_s, named=split is None)
            finally:
                for server in servers:
                    server.stop(0.5)
            row = {"scheduler": sched, "setup": setup, "shares": split, **summarise(stats)}
            rows.append(row)
            print(
                f"{sched:10s} {setup:13s} " + "  ".join(f"{k} {v:5.1f}%" for k, v in row.items() if "/" in k or k == "all"),
                flush=True,
            )
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"command": " ".join(sys.argv), "profiles_ms": PROFILES_MS, "rows": rows}, indent=2) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
