"""Multi-GPU simulation, fleet files and ``lerobot-armory-plan``."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.sim.cluster import place_fleet, simulate_cluster
from lerobot_armory.sim.fleet_file import Fleet, RobotGroup, fleet_from_dict, load_fleet
from lerobot_armory.sim.plan import main as plan_main

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "fleets"


def libero(fast: int, slow: int, **kwargs) -> Fleet:
    groups = []
    if fast:
        groups.append(RobotGroup("fast", fast, 20.0, 10, 1, 6, 3.0, "fast"))
    if slow:
        groups.append(RobotGroup("slow", slow, 20.0, 10, 1, 10, 1.0, "slow"))
    return Fleet(tuple(groups), "l40s-pi05", 3, **kwargs)


def plan(argv: list[str], capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        plan_main(argv)
    out, err = capsys.readouterr()
    return exc.value.code, out, err


def test_a_small_cluster_simulates_every_replica():
    fleet = libero(4, 4)
    result = simulate_cluster(fleet, 2, "mirror_aware", seed=0, duration_s=10.0)
    assert result.gpus == 2 and len(result.replicas) == 2
    assert sorted(result.robots_per_replica) == [4, 4]
    placed = sorted(rid for r in result.replicas for rid in r.robot_ids)
    assert placed == sorted(s.robot_id for s in fleet.specs())
    for tier in ("fast", "slow"):
        assert 0.0 <= result.tier_starvation_pct(tier) <= 100.0
        # the fleet figure is the ticks-weighted mean of the replicas'
        assert min(r.tier_starvation_pct(tier) for r in result.replicas) <= result.tier_starvation_pct(tier)
    assert result.worst_replica_pct("fast") == max(r.tier_starvation_pct("fast") for r in result.replicas)
    assert 1 <= result.simulations <= 2
    json.dumps(result.record())  # serialisable


def test_more_gpus_starve_a_loaded_fleet_less():
    fleet = libero(6, 6)  # ≈ 2.7 GPUs of predicted demand
    few = simulate_cluster(fleet, 2, seed=0, duration_s=20.0)
    many = simulate_cluster(fleet, 6, seed=0, duration_s=20.0)
    assert max(few.utilizations) > 1.0 > max(many.utilizations)
    assert many.tier_starvation_pct("fast") < few.tier_starvation_pct("fast") - 10.0
    assert many.tier_starvation_pct("slow") < few.tier_starvation_pct("slow")


def test_identical_replicas_are_simulated_once_unless_asked_otherwise():
    fleet = libero(0, 12)
    cache: dict = {}
    shared = simulate_cluster(fleet, 4, "round_robin", seed=1, duration_s=10.0, cache=cache)
    assert shared.simulations == 1 and sum(r.simulated for r in shared.replicas) == 1
    again = simulate_cluster(fleet, 4, "round_robin", seed=1, duration_s=10.0, cache=cache)
    assert again.simulations == 0  # reused across calls through the cache
    assert again.tier_starvation_pct("slow") == shared.tier_starvation_pct("slow")
    each = simulate_cluster(fleet, 4, "round_robin", seed=1, duration_s=10.0, distinct_only=False)
    assert each.simulations == 4


def test_mirror_aware_is_no_worse_than_random_where_random_clusters_fast_robots():
    fleet = libero(8, 8)
    for seed in range(4):
        rand = place_fleet(fleet, 4, "random", seed)
        if max(sum(s.tier == "fast" for s in r.robots.values()) for r in rand) >= 4:
            break
    else:
        pytest.fail("random never clustered fast robots for these seeds")
    aware = place_fleet(fleet, 4, "mirror_aware", seed)
    assert [sum(s.tier == "fast" for s in r.robots.values()) for r in aware] == [2, 2, 2, 2]
    r_rand = simulate_cluster(fleet, 4, "random", seed=seed, duration_s=20.0)
    r_aware = simulate_cluster(fleet, 4, "mirror_aware", seed=seed, duration_s=20.0)
    assert r_aware.tier_starvation_pct("fast") <= r_rand.tier_starvation_pct("fast")
    assert r_aware.worst_replica_pct("fast") < r_rand.worst_replica_pct("fast")


def test_heterogeneous_gpus_and_the_robot_limit():
    fleet = libero(2, 10)
    result = simulate_cluster(fleet, 2, seed=0, duration_s=5.0, profiles=["h100-pi05", "l40s-pi05"])
    by = {r.profile: r.robots for r in result.replicas}
    assert by["h100-pi05"] > by["l40s-pi05"]
    with pytest.raises(ConfigError, match="max_robots_per_gpu"):
        simulate_cluster(libero(2, 10, max_robots_per_gpu=5), 2, duration_s=5.0)
    with pytest.raises(ConfigError, match="profiles"):
        simulate_cluster(fleet, 2, duration_s=5.0, profiles=["h100-pi05"])


def test_example_fleet_files_and_the_preset_shorthand_load():
    files = sorted(EXAMPLES.glob("*.y*ml")) + sorted(EXAMPLES.glob("*.json"))
    assert len(files) >= 3
    for path in files:
        fleet = load_fleet(str(path))
        assert fleet.robots > 0 and fleet.total_demand() > 0
    fleet = load_fleet("preset:piper:one-fast:40:5")
    assert fleet.tier_counts() == {"fast": 1, "slow": 39}
    assert (fleet.max_batch_size, fleet.latency_profile, fleet.scheduler.type) == (5, "l40s-pi05", "edf")
    assert [g.weight for g in fleet.groups] == [5.0, 1.0]
    for bad in ("preset:libero", "preset:nope:half-fast:4", "preset:libero:half-fast:x", "preset:libero:half-fast:0"):
        with pytest.raises(ConfigError):
            load_fleet(bad)


GOOD = {
    "latency_profile": "l40s-pi05",
    "max_batch_size": 3,
    "robots": [{"count": 2, "fps": 20, "chunk_size": 10, "h_min": 1, "h_max": 6, "tier": "fast"}],
}


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"gpus": 3}, "gpus"),
        ({"max_batch_size": 0}, "max_batch_size"),
        ({"max_batch_size": True}, "max_batch_size"),
        ({"latency_profile": "no-such-gpu"}, "latency_profile"),
        ({"scheduler": "fifo"}, "scheduler"),
        ({"scheduler": {"type": "lookahead", "dept": 2}}, "scheduler"),
        ({"scheduler": {"type": "lookahead", "depth": 0}}, "scheduler.depth"),
        ({"network": {"median_ms": -1}}, "network.median_ms"),
        ({"network": {"jitter": 1}}, "network.jitter"),
        ({"robots": []}, "robots"),
        ({"robots": [{"count": 2, "fps": 20, "chunk_size": 10, "h_min": 1, "h_max": 12}]}, "robots[0].h_max"),
        ({"robots": [{"count": 0, "fps": 20, "chunk_size": 10, "h_min": 1, "h_max": 6}]}, "robots[0].count"),
        ({"robots": [{"count": 1, "fps": "20", "chunk_size": 10, "h_min": 1, "h_max": 6}]}, "robots[0].fps"),
        (
            {"robots": [{"count": 1, "fps": 20, "chunk_size": 10, "h_min": 1, "h_max": 6, "tier": "medium"}]},
            "robots[0].tier",
        ),
        ({"robots": [{"count": 1, "fps": 20, "chunk_size": 10, "h_max": 6}]}, "robots[0].h_min"),
        (
            {"robots": [{"count": 1, "fps": 20, "chunk_size": 10, "h_min": 1, "h_max": 6, "colour": "red"}]},
            "robots[0].colour",
        ),
    ],
)
def test_a_bad_fleet_file_names_the_field(change, field):
    with pytest.raises(ConfigError) as exc:
        fleet_from_dict({**GOOD, **change}, "f.yaml")
    assert exc.value.field == field
    assert "f.yaml" in str(exc.value)


def test_plan_answers_for_a_preset_in_seconds(capsys, tmp_path):
    start = time.perf_counter()
    out_file = tmp_path / "plan.json"
    code, out, err = plan(
        [
            "--fleet=preset:libero:half-fast:24",
            "--target_fast_pct=10",
            "--seeds=1",
            "--duration_s=15",
            f"--output={out_file}",
        ],
        capsys,
    )
    wall = time.perf_counter() - start
    assert code == 0, err
    assert wall < 10.0
    match = re.search(r"this fleet needs (\d+) GPUs of l40s-pi05 \(b=3, edf\) for fast-tier starvation ≤ 10 %", out)
    assert match, out
    answer = int(match.group(1))
    record = json.loads(out_file.read_text())
    assert record["answer"] == answer
    points = {p["gpus"]: p for p in record["points"] if p["placement"] == "mirror_aware"}
    assert points[answer]["fast_pct"] <= 10.0
    assert answer - 1 in points and points[answer - 1]["fast_pct"] > 10.0  # verified: one GPU fewer misses
    assert answer + 1 in points and points[answer + 1]["fast_pct"] <= 10.0  # and one more still meets
    assert record["lower_bound"] == pytest.approx(record["total_demand_gpus"], abs=1.0)
    assert "K=" in err and "searched K" in out


def test_plan_exits_1_when_max_gpus_is_too_few(capsys):
    code, out, _err = plan(
        ["--fleet=preset:libero:half-fast:24", "--max_gpus=2", "--seeds=1", "--duration_s=10"], capsys
    )
    assert code == 1
    assert "even --max_gpus=2 GPUs" in out and "miss" in out


def test_plan_exits_2_with_one_line_for_a_bad_fleet_file(capsys, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "latency_profile: l40s-pi05\nmax_batch_size: 3\nrobots:\n  - {count: 4, fps: 20, chunk_size: 10, h_min: 1, h_max: 12}\n"
    )
    code, _out, err = plan([f"--fleet={bad}"], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "robots[0].h_max" in lines[0] and "chunk size" in lines[0], err
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    code, _out, err = plan([f"--fleet={broken}"], capsys)
    assert code == 2 and "does not parse" in err
    code, _out, err = plan(["--fleet=preset:libero:half-fast:4", "--placement=nearest"], capsys)
    assert code == 2 and "placement" in err
