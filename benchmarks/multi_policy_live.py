"""Two policies on one device, live: one server serving both (``--policies``) against two servers,
one per policy, each given part of the device.

The fleet: libero timing (H = 10, 20 fps, h_min 1, h_max 6 fast / 10 slow),
``--robots_per_policy`` robots per policy, half of each fast (weight 3). ``--setup=h100`` (the
simulator study's profiles): policy ``pi05`` takes openpi's π0.5 on an H100 (42–87 ms at
b = 1..5, cap 5), ``act`` a flat 10 ms (cap 8); ``--setup=l40s``: π0.5 on an L40S (73 / 110 /
142 ms, cap 3) and ACT 13.8 ms (cap 3). Both run the tiny random ACT on the CPU, padded to
their profile (``EmulatedLatencyEngine``; batches where the CPU model ran longer are counted).

- *mixed*: one server, both policies, one device: each batch holds one policy's robots, the
  arbiter picks whose batch runs next.
- *split, even*: two servers, each with half the device (its profile ×2: a batch takes twice as
  long when the device runs two servers' batches interleaved).
- *split, by demand*: two servers, the device divided in proportion to each policy's demand
  (robots' chunks per second × d_infer(cap) / cap), computed from the fleet and the profiles.

Robots run the real client loop (``ArmoryClient``) in threads of this process over loopback
gRPC; starvation per policy and tier is what they report. Prints the table, writes JSON, exits 1
only on an error (a loss is a finding, reported as such).

    .venv/bin/python benchmarks/multi_policy_live.py --setup=h100 --robots_per_policy=8 --out=docs/results/multi_policy/live_h100.json
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

FPS, H, H_MIN, H_FAST, H_SLOW, FAST_WEIGHT = 20.0, 10, 1, 6, 10, 3.0
# Two device set-ups: "l40s" (the first run: π0.5 on an L40S, ACT's H100 b = 1 figure, cap 3 each)
# and "h100" (the simulator study's, docs/results/multi_policy: openpi's π0.5 on an H100, cap 5;
# ACT a flat 10 ms, cap 8).
SETUPS = {
    "l40s": {"pi05": ((73.0, 109.8, 142.4), 3), "act": ((13.8, 13.8, 13.8), 3)},
    "h100": {"pi05": ((42.3, 56.0, 66.1, 79.3, 87.2), 5), "act": ((10.0,) * 8, 8)},
}
PROFILES_MS: dict[str, tuple[float, ...]] = {}
CAPS: dict[str, int] = {}


def demand_share(robots_per_policy: int) -> dict[str, float]:
    """Each policy's share of device time its robots need, at full batches: chunks/s × d_infer(cap)/cap."""
    fast = robots_per_policy // 2
    chunks_s = fast * FPS / H_FAST + (robots_per_policy - fast) * FPS / H_SLOW
    need = {name: chunks_s * ms[CAPS[name] - 1] / 1000.0 / CAPS[name] for name, ms in PROFILES_MS.items()}
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
    engine.warmup(CAPS[name], log_progress=False)
    profile = LatencyProfile(name, profile_ms)
    info = PolicyInfo(engine.description, engine.wire_features, engine.action_names, engine.chunk_size)
    return EmulatedLatencyEngine(engine, profile), info, profile


def grant_rules() -> Any:
    """Grants the fast robots their weight of 3 (the built-in policy caps every weight at 1)."""
    from lerobot_armory.serving.grant_rules import GrantRules

    return GrantRules.from_dict({"default": {"max_weight": FAST_WEIGHT}}, "multi_policy_live")


def scheduler_config(name: str) -> Any:
    """The scheduler called ``name`` with its defaults (rr, edf, lookahead, rollout, ...)."""
    from lerobot_armory.schedulers import make_scheduler_config

    return make_scheduler_config(name)


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
    p.add_argument("--setup", default="h100", choices=tuple(SETUPS), help="profiles and caps (see SETUPS)")
    p.add_argument(
        "--time_scale", type=float, default=1.0,
        help="run the whole fleet this many times slower (profiles x k, fps / k): the same schedule, "
        "with room for the CPU model to stay inside its profile on a 2-core machine",
    )  # fmt: skip
    args = p.parse_args()
    global FPS
    FPS = FPS / args.time_scale
    for name, (ms, cap) in SETUPS[args.setup].items():
        PROFILES_MS[name], CAPS[name] = tuple(x * args.time_scale for x in ms), cap

    from lerobot_armory.entrypoints.server import ArmoryServer, ExtraPolicy, tune_process
    from lerobot_armory.demo.build import DemoPolicyConfig, make_demo_policy

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
                        e1, i1, p1, scheduler_config(sched), CAPS[names[0]], port=0, grant_rules=grant_rules(), policy_name=names[0],
                        others=(ExtraPolicy(names[1], e2, i2, p2, CAPS[names[1]]),),
                    ).start()  # fmt: skip
                    servers.append(server)
                    emulated = [e1, e2]
                    addresses = {n: server.address for n in names}
                    features = {f.name: (f.dtype, f.shape) for f in i1.wire_features}
                else:
                    addresses, emulated = {}, []
                    for name in PROFILES_MS:
                        scaled = tuple(ms / split[name] for ms in PROFILES_MS[name])
                        engine, info, profile = engine_for(paths[name], scaled, name)
                        emulated.append(engine)
                        server = ArmoryServer(engine, info, profile, scheduler_config(sched), CAPS[name], port=0, grant_rules=grant_rules()).start()
                        servers.append(server)
                        addresses[name] = server.address
                        features = {f.name: (f.dtype, f.shape) for f in info.wire_features}
                stats = run_fleet(addresses, features, args.robots_per_policy, args.duration_s, named=split is None)
            finally:
                for server in servers:
                    server.stop(0.5)
            # Batches the CPU model ran past its profile (then the device time is the model's, not the profile's).
            overruns = {"batches": sum(e.batches for e in emulated), "overruns": sum(e.overruns for e in emulated)}
            row = {"scheduler": sched, "setup": setup, "shares": split, **summarise(stats), **overruns}
            rows.append(row)
            print(
                f"{sched:10s} {setup:13s} " + "  ".join(f"{k} {v:5.1f}%" for k, v in row.items() if "/" in k or k == "all")
                + f"  (overran the profile: {row['overruns']} of {row['batches']} batches)",
                flush=True,
            )
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        meta = {"command": " ".join(sys.argv), "profiles_ms": PROFILES_MS, "caps": CAPS, "fps": FPS, "time_scale": args.time_scale}
        Path(args.out).write_text(json.dumps({**meta, "rows": rows}, indent=2) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
