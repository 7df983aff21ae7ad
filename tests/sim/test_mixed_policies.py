"""Fleets whose robots are served by several policies sharing one device (fleet files, simulator, CLIs)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from lerobot_armory.errors import ConfigError
from lerobot_armory.inference_latency import load_profile
from lerobot_armory.sim.cli import main as sim_main
from lerobot_armory.placement import demand
from lerobot_armory.sim.cluster import composition, place_fleet, simulate_cluster
from lerobot_armory.sim.fleet_file import fleet_from_dict, load_fleet
from lerobot_armory.sim.plan import main as plan_main
from lerobot_armory.sim.run import fleet_simulator
from lerobot_armory.sim.simulator import FleetSimulator

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "fleets"
FAST = {"fps": 20, "chunk_size": 10, "h_min": 1, "h_max": 6, "tier": "fast", "weight": 3}
SLOW = {"fps": 20, "chunk_size": 10, "h_min": 1, "h_max": 10, "tier": "slow"}


def mixed(scheduler: str = "edf", **top) -> dict:
    """A small mixed fleet: a slow π0.5-like policy and a fast, flat one (built-in profiles only)."""
    return {
        "scheduler": scheduler,
        "policies": {
            "pi05": {"latency_profile": "l40s-pi05", "max_batch_size": 3},
            "groot": {"latency_profile": "l40s-groot", "max_batch_size": 5},
        },
        "robots": [
            {"name": "pf", "count": 3, "policy": "pi05", **FAST},
            {"name": "ps", "count": 3, "policy": "pi05", **SLOW},
            {"name": "gf", "count": 3, "policy": "groot", **FAST},
            {"name": "gs", "count": 3, "policy": "groot", **SLOW},
        ],
        **top,
    }


def test_a_mixed_fleet_file_loads():
    fleet = load_fleet(str(EXAMPLES / "libero-mixed-policies-20.yaml"))
    assert fleet.is_mixed
    assert [(p.name, p.max_batch_size) for p in fleet.policies] == [("pi05", 5), ("act", 8)]
    assert fleet.policies[1].profile().latency_ms == (10.0,) * 8  # the JSON beside the fleet file
    assert fleet.policy_counts() == {"pi05": 10, "act": 10}
    assert set(fleet.policy_of().values()) == {"pi05", "act"} and len(fleet.policy_of()) == 20
    assert "pi05: 10 robots on h100-pi05, b=5" in fleet.describe()


def test_a_policy_may_inherit_the_top_level_profile_and_cap():
    data = mixed(latency_profile="l40s-groot", max_batch_size=4)
    data["policies"]["groot"] = {}
    groot = fleet_from_dict(data, "f.yaml").policies[1]
    assert (groot.latency_profile, groot.max_batch_size) == ("l40s-groot", 4)


@pytest.mark.parametrize(
    "change, field",
    [
        (lambda d: d["robots"][2].update(policy="nope"), "robots[2].policy"),
        (lambda d: d["robots"][0].pop("policy"), "robots[0].policy"),
        (lambda d: d["policies"]["pi05"].pop("latency_profile"), "policies.pi05.latency_profile"),
        (lambda d: d["policies"]["pi05"].pop("max_batch_size"), "policies.pi05.max_batch_size"),
        (lambda d: d["policies"]["pi05"].update(latency_profile="no-such-gpu"), "policies.pi05.latency_profile"),
        (lambda d: d["policies"]["pi05"].update(max_batch_size=0), "policies.pi05.max_batch_size"),
        (lambda d: d["policies"]["pi05"].update(speed=3), "policies.pi05.speed"),
        (lambda d: d.update(policies=[]), "policies"),
        (lambda d: d.pop("policies"), "latency_profile"),  # groups name policies nobody defines
    ],
)
def test_bad_mixed_fleets_name_the_field(change, field):
    data = mixed()
    change(data)
    with pytest.raises(ConfigError) as exc:
        fleet_from_dict(data, "f.yaml")
    assert exc.value.field == field


def test_a_group_naming_a_policy_without_policies_is_refused():
    data = mixed(latency_profile="l40s-pi05", max_batch_size=3)
    data.pop("policies")
    with pytest.raises(ConfigError) as exc:
        fleet_from_dict(data, "f.yaml")
    assert exc.value.field == "robots[0].policy" and "no policies" in exc.value.message


def test_a_policy_no_group_uses_is_fine():
    data = mixed()
    data["policies"]["spare"] = {"latency_profile": "h100-pi05", "max_batch_size": 2}
    fleet = fleet_from_dict(data, "f.yaml")
    assert fleet.policy_counts()["spare"] == 0
    result = fleet_simulator(fleet, 3.0, seed=0).run()
    assert result.policy_batch_sizes["spare"] == {} and result.device_s["spare"] == 0.0


@pytest.mark.parametrize("scheduler", ["rr", "edf", "lookahead"])
def test_every_batch_is_one_policy_at_its_own_latency(scheduler):
    fleet = fleet_from_dict(mixed(scheduler), "f.yaml")
    result = fleet_simulator(fleet, 10.0, seed=1, trace=True).run()
    policy_of = fleet.policy_of()
    table = {p.name: p.profile().table_s(p.max_batch_size) for p in fleet.policies}
    assert result.batches and {b.policy for b in result.batches} == {"pi05", "groot"}
    for batch in result.batches:
        assert {policy_of[r] for r in batch.robot_ids} == {batch.policy}
        assert len(batch.robot_ids) <= dict((p.name, p.max_batch_size) for p in fleet.policies)[batch.policy]
        assert batch.t_done - batch.t_start == pytest.approx(table[batch.policy][len(batch.robot_ids) - 1], abs=1e-12)
    for before, after in zip(result.batches, result.batches[1:]):  # one device: batches never overlap
        assert after.t_start >= before.t_done - 1e-12
    for name in table:
        sizes = result.policy_batch_sizes[name]
        assert sum(sizes.values()) == sum(b.policy == name for b in result.batches)
        busy = sum(b.t_done - b.t_start for b in result.batches if b.policy == name)
        assert result.device_s[name] == pytest.approx(busy)
    assert all(r.policy in table for r in result.robots)


def test_one_named_policy_is_the_same_fleet_as_none():
    plain = mixed("lookahead", latency_profile="l40s-pi05", max_batch_size=3)
    plain.pop("policies")
    for group in plain["robots"]:
        group.pop("policy")
    named = mixed("lookahead")
    named["policies"] = {"pi05": {"latency_profile": "l40s-pi05", "max_batch_size": 3}}
    for group in named["robots"]:
        group["policy"] = "pi05"
    a, b = fleet_from_dict(plain, "f.yaml"), fleet_from_dict(named, "f.yaml")
    assert not b.is_mixed and a.specs() == b.specs()
    ra = fleet_simulator(a, 8.0, seed=2).run()
    rb = fleet_simulator(b, 8.0, seed=2).run()
    assert [(r.robot_id, r.ticks, r.executed_steps, r.chunks_received) for r in ra.robots] == [
        (r.robot_id, r.ticks, r.executed_steps, r.chunks_received) for r in rb.robots
    ]
    assert ra.batch_sizes == rb.batch_sizes and ra.mirror_index_error == rb.mirror_index_error


def test_a_slow_policy_changes_what_the_fast_one_gets():
    """The arbiter really shares one device: slowing the other policy starves this one more."""
    light = mixed("edf")
    heavy = mixed("edf")
    heavy["policies"]["pi05"]["max_batch_size"] = 1  # π0.5 now needs far more device time
    heavy["robots"][0]["count"] = heavy["robots"][1]["count"] = 8
    a = fleet_simulator(fleet_from_dict(light, "f.yaml"), 20.0, seed=0).run()
    b = fleet_simulator(fleet_from_dict(heavy, "f.yaml"), 20.0, seed=0).run()
    assert b.policy_starvation_pct("groot") > a.policy_starvation_pct("groot")


def test_sim_cli_runs_a_mixed_fleet(tmp_path, capsys):
    out = tmp_path / "mixed.json"
    fleet = EXAMPLES / "libero-mixed-policies-20.yaml"
    sim_main([f"--fleet={fleet}", "--duration_s=3", "--seeds=2", f"--output={out}"])
    runs = json.loads(out.read_text())["runs"]
    assert [r["seed"] for r in runs] == [0, 1]
    assert set(runs[0]["policies"]) == {"pi05", "act"}
    act = runs[0]["policies"]["act"]
    assert act["robots"] == 10 and act["latency_profile"].endswith("act-h100.json")
    text = capsys.readouterr().out
    assert "  pi05" in text and "  act" in text


def test_placement_charges_each_robot_its_own_policys_cost():
    fleet = fleet_from_dict(mixed(), "f.yaml")
    caps = fleet.policy_capacities()
    pf, gf = fleet.specs()[0], fleet.specs()[6]  # a fast π0.5 robot and a fast GR00T robot, same timing
    replicas = place_fleet(fleet, 2, "mirror_aware", seed=0)
    view = replicas[0]
    assert view.demand(pf) == pytest.approx(demand(pf, caps["pi05"]))
    assert view.demand(gf) == pytest.approx(demand(gf, caps["groot"]))
    assert view.demand(pf) != pytest.approx(view.demand(gf))
    # the load model sums each robot at its own policy's cost, and so does the fleet's total
    assert sum(v.utilization() for v in replicas) == pytest.approx(fleet.total_demand())


def test_mirror_aware_balances_the_load_at_each_policys_cost():
    data = mixed()
    data["robots"] = [{"name": "p", "count": 4, "policy": "pi05", **FAST}, {"name": "g", "count": 4, "policy": "groot", **FAST}]
    fleet = fleet_from_dict(data, "f.yaml")
    heaviest = max(demand(s, c) for s in fleet.specs() for c in fleet.policy_capacities().values())
    for seed in range(5):
        # greedy on predicted load, each robot at its policy's cost: the GPUs end within one robot
        loads = [v.utilization() for v in place_fleet(fleet, 2, "mirror_aware", seed=seed)]
        assert max(loads) - min(loads) <= heaviest + 1e-9, (seed, loads)
    blind = [v.utilization() for v in place_fleet(fleet, 2, "least_loaded", seed=0)]
    assert sum(blind) == pytest.approx(fleet.total_demand())


def test_a_cluster_of_one_gpu_serves_the_whole_mixed_fleet_on_one_device():
    fleet = fleet_from_dict(mixed(), "f.yaml")
    one = simulate_cluster(fleet, 1, seed=0, duration_s=10.0)
    alone = fleet_simulator(fleet, 10.0, seed=0).run()
    assert one.replicas[0].robots == fleet.robots
    # the same robots, ticks and (per composition) simulation: the ticks agree exactly
    assert sum(one.replicas[0].ticks.values()) == sum(r.ticks for r in alone.robots)


def test_compositions_differ_by_policy():
    fleet = fleet_from_dict(mixed(), "f.yaml")
    pf, gf = fleet.specs()[0], fleet.specs()[6]
    policy_of = fleet.policy_of()
    assert composition([pf]) == composition([replace(gf, robot_id=pf.robot_id)])  # same timing
    assert composition([pf], policy_of) != composition([gf], policy_of)


@pytest.mark.slow
def test_plan_a_mixed_fleet(tmp_path, capsys):
    out = tmp_path / "plan.json"
    with pytest.raises(SystemExit) as exc:
        plan_main([f"--fleet={EXAMPLES / 'libero-mixed-policies-20.yaml'}", "--duration_s=10", f"--output={out}"])
    code = exc.value.code
    text = capsys.readouterr().out
    record = json.loads(out.read_text())
    assert code == 0 and record["answer"] >= 1
    assert set(record["policies"]) == {"pi05", "act"} and record["latency_profile"] is None
    assert "pi05 h100-pi05 b=5 + act" in text and "arbitrated" in text
    # and the other way: each policy's robots on GPUs of their own, compared in one line
    split = record["split"]
    assert set(split["gpus"]) == {"pi05", "act"} and split["total"] == sum(split["gpus"].values())
    assert f"one set of GPUs per policy instead: pi05 {split['gpus']['pi05']} + act {split['gpus']['act']}" in text


def test_one_policys_robots_alone_are_a_one_policy_fleet():
    fleet = fleet_from_dict(mixed(), "f.yaml")
    alone = fleet.only("groot")
    assert not alone.is_mixed and alone.robots == 6 and alone.latency_profile == "l40s-groot" and alone.max_batch_size == 5
    assert [s.robot_id for s in alone.specs()] == [s.robot_id for s in fleet.specs() if fleet.policy_of()[s.robot_id] == "groot"]
    with pytest.raises(ConfigError, match="no policy 'nope'"):
        fleet.only("nope")


@pytest.mark.slow
def test_a_heavier_policy_mix_needs_at_least_as_many_gpus(tmp_path):
    def fleet_file(pi05: int, act: int) -> Path:
        data = {
            "scheduler": "edf",
            "policies": {"pi05": {"latency_profile": "h100-pi05", "max_batch_size": 5},
                         "act": {"latency_profile": str(EXAMPLES.parent / "profiles" / "act-h100.json"), "max_batch_size": 8}},
            "robots": [{"name": "p", "count": pi05, "policy": "pi05", **FAST},
                       {"name": "a", "count": act, "policy": "act", **FAST}],
        }  # fmt: skip
        path = tmp_path / f"f{pi05}.json"
        path.write_text(json.dumps(data))
        return path

    answers = []
    for pi05, act in ((6, 30), (30, 6)):
        out = tmp_path / f"plan{pi05}.json"
        with pytest.raises(SystemExit):
            plan_main([f"--fleet={fleet_file(pi05, act)}", "--duration_s=10", "--seeds=1", f"--output={out}"])
        answers.append(json.loads(out.read_text()))
    light, heavy = answers
    assert heavy["total_demand_gpus"] > 2 * light["total_demand_gpus"]
    assert heavy["answer"] > light["answer"]


def test_plan_refuses_a_profile_override_for_a_mixed_fleet_in_one_line(capsys):
    with pytest.raises(SystemExit) as exc:
        plan_main([f"--fleet={EXAMPLES / 'libero-mixed-policies-20.yaml'}", "--latency_profile=h100-pi05"])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1
    assert "policies: entry" in err


def test_the_act_profile_is_a_valid_profile_file():
    assert load_profile(str(EXAMPLES.parent / "profiles" / "act-h100.json")).latency_s(8) == pytest.approx(0.010)


def test_sim_cli_bad_mixed_fleet_is_one_line_naming_the_field(tmp_path, capsys):
    data = mixed()
    data["robots"][1]["policy"] = "nope"
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(SystemExit) as exc:
        sim_main([f"--fleet={path}", "--duration_s=2"])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and len(err.splitlines()) == 1 and "robots[1].policy: unknown policy 'nope'" in err


def test_the_simulator_needs_each_robots_policy():
    fleet = fleet_from_dict(mixed(), "f.yaml")
    schedulers = {p.name: fleet.scheduler.make(p.profile(), p.max_batch_size) for p in fleet.policies}
    net = fleet.network()
    with pytest.raises(ConfigError, match="policy_of"):
        FleetSimulator(fleet.specs(), schedulers, 2.0, net, net)
    partial = dict(list(fleet.policy_of().items())[1:])  # the first robot has no policy
    with pytest.raises(ConfigError, match="pf-000"):
        FleetSimulator(fleet.specs(), schedulers, 2.0, net, net, policy_of=partial)


def test_the_plan_target_holds_for_every_policy_not_only_the_fleet_mean():
    from lerobot_armory.sim.plan import Planner, PlanConfig, Point

    fleet = fleet_from_dict(mixed(), "f.yaml")
    runs = [simulate_cluster(fleet, 1, seed=s, duration_s=10.0) for s in (0, 1)]
    point = Point(1, "mirror_aware", runs)
    by_policy = {p: point.policy_pct(p, "fast") for p in ("pi05", "groot")}
    worst, best = max(by_policy.values()), min(by_policy.values())
    assert best < point.fast_pct < worst  # the fleet's mean sits between its policies
    between = (point.fast_pct + worst) / 2  # met by the fleet's mean, missed by the worst policy
    assert not Planner(fleet, PlanConfig(target_fast_pct=between)).meets(point)
    assert Planner(fleet, PlanConfig(target_fast_pct=worst + 0.01)).meets(point)
    assert runs[0].record()["policies"].keys() == {"pi05", "groot"}


def test_rollout_beside_a_slow_policy_does_not_starve_either():
    """Rollout plans the whole shared device (docs/results/multi_policy, "Rollout across policies").

    The study's `half` fleet at N = 16 (π0.5 on the H100 profile, cap 5, beside a flat 10 ms ACT,
    cap 8; half of each policy's robots fast-tier). When each Rollout planned as if the device were
    its own, ACT served its robots one or two at a time, just in time (10 ms whatever the size), so
    an ACT robot left out waited behind an 87 ms π0.5 batch, and the π0.5 batches were small too:
    8 s here starved ACT 4.8 % and π0.5 6.8 % (seed 0). Seeing the other policy, neither should."""
    fleet = {
        "scheduler": "rollout",
        "policies": {
            "pi05": {"latency_profile": "h100-pi05", "max_batch_size": 5},
            "act": {"latency_profile": str(EXAMPLES.parent / "profiles" / "act-h100.json"), "max_batch_size": 8},
        },
        "robots": [
            {"name": f"{policy}-{tier['tier']}", "count": 4, "policy": policy, **tier}
            for policy in ("pi05", "act")
            for tier in (FAST, SLOW)
        ],
    }
    result = fleet_simulator(fleet_from_dict(fleet, "f.yaml"), 8.0, seed=0, warmup_s=2.0).run()
    assert result.policy_starvation_pct("act") < 1.0
    assert result.policy_starvation_pct("pi05") < 3.0
