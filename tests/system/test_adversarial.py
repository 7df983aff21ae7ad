"""One robot cannot hurt the fleet: each attack of ``tests/support/adversaries.py``, briefly, next to
a few honest light robots on an in-process server, then a fuzzer of mutated messages.

Every test checks that the serving loop is alive and never failed, and that the honest robots
kept being served: their starvation stays within ``MARGIN_PP`` of the same robots without the
attacker (measured once per server set-up and cached; a loaded 2-core machine is noisy, and an
attack that works shows tens of points or a dead loop). The benchmark (``benchmarks/adversarial.py``)
measures the same attacks on the real server process with a 2-point bound.
"""

from __future__ import annotations

import math
import random
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.support.echo import EchoEngine
from lerobot_armory.inference_latency import LatencyProfile
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.robot.client import ArmoryClient, Backoff, RobotIdentity
from lerobot_armory.schedulers import make_scheduler_config
from lerobot_armory.entrypoints.server import ArmoryServer
from lerobot_armory.serving.security import AuthTokens
from lerobot_armory.entrypoints.grpc.service import PolicyInfo
from lerobot_armory.wire import FeatureSpec

from tests.support import adversaries as adv

STATE = {"observation.state": ("float32", (4,))}
WITH_IMAGE = {"observation.state": ("float32", (4,)), "observation.images.front": ("uint8", (32, 32, 3))}
HONEST_S = 3.0
MARGIN_PP = 10.0
ACCEPTABLE_REGISTER_CODES = {"OK", "INVALID_ARGUMENT", "ALREADY_EXISTS", "RESOURCE_EXHAUSTED"}


# ---- set-up ------------------------------------------------------------------------------------


def make_server(scheduler: str = "lookahead", cap: int = 3, delay_s: float = 0.03, features=STATE, **kwargs: Any) -> ArmoryServer:
    """An in-process server whose engine answers each robot with its first state value after
    ``delay_s`` (the profile says so too), on a free port; 200 obs/s per robot like the CLI."""
    info = PolicyInfo("echo", [FeatureSpec(n, d, s) for n, (d, s) in features.items()], ["a", "b"], 10)
    profile = LatencyProfile("echo", tuple(1000.0 * delay_s * (1 + 0.3 * k) for k in range(cap)))
    kwargs.setdefault("max_obs_rate_hz", 200.0)
    return ArmoryServer(EchoEngine(delay_s), info, profile, make_scheduler_config(scheduler), cap, port=0, **kwargs).start()


@contextmanager
def serving(*args: Any, **kwargs: Any) -> Iterator[ArmoryServer]:
    """``make_server`` that is stopped at the end, within 10 s: a server whose graceful stop
    hangs after an attack fails the test (it is stopped on a background thread, never waited
    for longer)."""
    server = make_server(*args, **kwargs)
    failed = False
    try:
        yield server
    except BaseException:
        failed = True
        raise
    finally:
        stopper = threading.Thread(target=server.stop, args=(0.5,), daemon=True)
        stopper.start()
        stopper.join(10.0)
        if stopper.is_alive() and not failed:
            raise AssertionError("server.stop() did not return within 10 s after the attack (graceful shutdown hangs)")


def honest_client(address: str, name: str, value: float, features=STATE, **kwargs: Any) -> ArmoryClient:
    arrays = {n: np.zeros(s, dtype=d) for n, (d, s) in features.items()}
    arrays["observation.state"] = np.array([value, 0, 0, 0], np.float32)
    kwargs.setdefault("backoff", Backoff(0.2, 1.0, give_up_s=20.0))
    return ArmoryClient(address, RobotIdentity(name, fps=20.0, h_min=2, h_max=8), features, observe=lambda: arrays, act=lambda a: None, **kwargs)


def run_honest(
    address: str, n: int = 3, seconds: float = HONEST_S, features=STATE, tokens: dict[str, str] | None = None, clients: list | None = None
) -> list[dict[str, Any]]:
    """``n`` honest robots ticking for ``seconds`` from now (connected or not: ticks before the
    first chunk starve). Each result: id, timeline, starvation %, chunks, error, wrong chunks."""
    clients = clients or [
        honest_client(address, f"honest{k}", float(k + 1), features, token=(tokens or {}).get(f"honest{k}", "")) for k in range(n)
    ]
    results: list[dict[str, Any]] = [{} for _ in clients]

    def one(k: int, client: ArmoryClient) -> None:
        wrong = []
        original = client.buffer.add
        mine = float(client.observe()["observation.state"][0])

        def add(cid, i, actions, t):  # the echo engine answers with the robot's own value
            if not np.all(actions == mine):
                wrong.append(cid)
            return original(cid, i, actions, t)

        client.buffer.add = add
        tl = adv.run_ticks(client, seconds)
        client.close()
        results[k] = {
            "id": client.identity.robot_id, "timeline": tl, "starvation": tl.starvation_pct(), "chunks": client.chunks_received,
            "error": client.fatal, "wrong": wrong,
        }  # fmt: skip

    threads = [threading.Thread(target=one, args=(k, c)) for k, c in enumerate(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


def mean_starvation(results: list[dict[str, Any]]) -> float:
    return float(np.mean([r["starvation"] if r["starvation"] is not None else 100.0 for r in results]))


_BASELINES: dict[tuple, float] = {}


def baseline(scheduler: str = "lookahead", cap: int = 3, delay_s: float = 0.03, features=STATE) -> float:
    """Mean honest starvation without an attacker for this set-up (measured once per session)."""
    key = (scheduler, cap, delay_s, tuple(features))
    if key not in _BASELINES:
        server = make_server(scheduler, cap, delay_s, features)
        try:
            _BASELINES[key] = mean_starvation(run_honest(server.address, features=features))
        finally:
            server.stop(0.5)
    return _BASELINES[key]


def attack_while_honest_run(
    server: ArmoryServer,
    scenario: str,
    features=STATE,
    lead_s: float = 0.5,
    honest: dict[str, Any] | None = None,
    **kwargs: Any,
) -> tuple[list[dict[str, Any]], adv.AttackReport]:
    """Start the attacker, give it ``lead_s``, run the honest robots, stop the attacker."""
    stop = threading.Event()
    report = adv.AttackReport(scenario)
    errors: list[BaseException] = []

    def attack() -> None:
        try:
            adv.SCENARIOS[scenario](server.address, stop, features, report, **kwargs)
        except BaseException as exc:  # noqa: BLE001 - re-raised in the test
            errors.append(exc)

    thread = threading.Thread(target=attack, name=f"attacker-{scenario}", daemon=True)
    thread.start()
    time.sleep(lead_s)
    try:
        results = run_honest(server.address, features=features, **(honest or {}))
    finally:
        stop.set()
        thread.join(timeout=20)
    assert not errors, f"the attacker itself failed: {errors[0]!r}"
    assert not thread.is_alive(), "the attacker did not stop"
    return results, report


def assert_fleet_unharmed(server: ArmoryServer, results: list[dict[str, Any]], base: float, report: adv.AttackReport) -> None:
    assert server.loop.alive and server.loop.error is None, f"serving loop died: {server.loop.error!r} ({report.summary()})"
    for r in results:
        assert r["error"] is None, f"{r['id']} could not run: {r['error']!r}"
        assert r["chunks"] > 0, f"{r['id']} never got a chunk ({report.summary()})"
        assert not r["wrong"], f"{r['id']} got another robot's chunk"
    starvation = mean_starvation(results)
    assert starvation <= base + MARGIN_PP, (
        f"honest starvation {starvation:.1f}% vs {base:.1f}% without the attacker ({report.summary()})"
    )
    assert not report.violations, f"the server broke a rule: {dict(report.violations)}"


# ---- one test per attack -----------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("scheduler", ["lookahead", "edf"])
@pytest.mark.parametrize("scenario", ["clock_nan", "capture_absurd", "report_absurd"])
def test_poisoned_times_do_not_hurt_the_fleet(scenario, scheduler):
    """NaN / inf / 1e308 in clock exchanges, capture times and execution reports."""
    base = baseline(scheduler)
    with serving(scheduler) as server:
        # report_absurd: a chunk every tick or so, so that many real receipts carry absurd times
        results, report = attack_while_honest_run(server, scenario, **({"h_min": 1} if scenario == "report_absurd" else {}))
        assert report.counts["messages"] > 20, report.summary()
        assert_fleet_unharmed(server, results, base, report)


@pytest.mark.slow
def test_absurd_registrations_are_refused_or_bounded():
    """fps 1e308 / 1e-308 / NaN, weight and horizon extremes: INVALID_ARGUMENT or a sane grant;
    whatever got in streams observations next to the honest robots."""
    base = baseline("lookahead")
    with serving("lookahead") as server:
        results, report = attack_while_honest_run(server, "fps_absurd")
        assert len(report.extra.get("outcomes", {})) == len(adv.ABSURD_REGISTRATIONS)
        assert_fleet_unharmed(server, results, base, report)


@pytest.mark.slow
def test_priority_flood_gets_no_priority():
    """Asks weight 3 and h_min 0, claims 190 steps/s at 20 fps. Tight device (b=1, 60 ms)."""
    base = baseline("lookahead", cap=1, delay_s=0.06)
    with serving("lookahead", cap=1, delay_s=0.06) as server:
        results, report = attack_while_honest_run(server, "priority_flood")
        assert report.counts["messages"] > 300, report.summary()
        assert_fleet_unharmed(server, results, base, report)


@pytest.mark.slow
def test_clock_ahead_gets_no_priority_under_edf():
    """Clock exchanges 10^6 s off the clock of its observations: the most urgent robot an EDF
    server ever saw, unless the server refuses the lie. EDF b=1, 60 ms batches."""
    base = baseline("edf", cap=1, delay_s=0.06)
    with serving("edf", cap=1, delay_s=0.06) as server:
        results, report = attack_while_honest_run(server, "clock_ahead")
        assert_fleet_unharmed(server, results, base, report)


@pytest.mark.slow
def test_huge_report_does_not_stall_the_fleet():
    """A 16 MiB execution report (~8.4 M receipts) every second."""
    base = baseline("lookahead")
    with serving("lookahead") as server:
        results, report = attack_while_honest_run(server, "huge_report", every_s=1.0)
        assert report.counts["huge reports"] >= 2, report.summary()
        assert_fleet_unharmed(server, results, base, report)


ECHO_SERVER_PROCESS = """
import sys
from tests.support.echo import echo_server
server = echo_server(max_obs_rate_hz=0.0)
print(server.address, flush=True)
sys.stdin.read()  # serve until the test closes stdin
server.stop(0.5)
"""


@contextmanager
def echo_server_process(nofile: int = 0) -> Iterator[tuple[subprocess.Popen, str]]:
    """An echo server (state-only robots, no rate limit) in a process of its own, so that its RSS
    and its open files are its own; ``nofile``: the soft fd limit it starts with (0: this one's)."""
    command = [sys.executable, "-c", ECHO_SERVER_PROCESS]
    if nofile:
        command = ["/bin/sh", "-c", f'ulimit -S -n {nofile} && exec "$0" "$@"', *command]
    proc = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        address = proc.stdout.readline().strip()
        assert address, "the echo server did not start"
        yield proc, address
    finally:
        try:
            if proc.stdin is not None:
                proc.stdin.close()
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def process_rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError(f"no VmRSS for {pid}")


@pytest.mark.slow
@pytest.mark.subprocess
def test_never_reading_robot_cannot_grow_server_memory():
    """Answers it never reads (notices echoing a 64 KiB tensor name): 150 MiB of bait, no rate
    limit so that it goes fast; the server's memory must not follow."""
    stop = threading.Event()
    report = adv.AttackReport("never_reads")
    thread: threading.Thread | None = None
    with echo_server_process() as (proc, address):
        try:
            run_honest(address, n=1, seconds=0.5)  # warm: the first robot's allocations are not the attack's
            before = process_rss_mib(proc.pid)
            thread = threading.Thread(
                target=adv.never_reads, args=(address, stop, STATE, report), kwargs={"total_bytes": 150 * adv.MIB, "rate_hz": 2000.0}
            )
            thread.start()
            deadline = time.monotonic() + 20
            while report.counts["bytes"] < 150 * adv.MIB and time.monotonic() < deadline and thread.is_alive():
                time.sleep(0.1)
            time.sleep(1.0)  # what is in flight reaches the server
            growth = process_rss_mib(proc.pid) - before
            results = run_honest(address, seconds=1.5)
        finally:
            stop.set()
            if thread is not None:
                thread.join(timeout=20)
        assert report.counts["bytes"] >= 150 * adv.MIB, f"only {report.counts['bytes'] / adv.MIB:.0f} MiB sent ({report.summary()})"
        assert growth < 100, f"server RSS grew {growth:.0f} MiB while a robot did not read its stream ({report.summary()})"
        assert proc.poll() is None, "the server process died"
        assert all(r["chunks"] > 0 for r in results), "honest robots were not served"


@pytest.mark.slow
def test_slot_squatter_cannot_keep_honest_robots_out():
    """Registrations that never stream fill every slot (max_robots=4) and are renewed twice a
    second; honest robots started after must still get in (the client retries RESOURCE_EXHAUSTED)."""
    with serving("lookahead", max_robots=4) as server:
        results, report = attack_while_honest_run(server, "slot_squat", lead_s=1.0, honest={"n": 2, "seconds": 8.0}, slots=4, extra=2)
        assert report.extra.get("most slots held", 0) >= 4 or report.codes.get("register RESOURCE_EXHAUSTED"), report.summary()
        assert server.loop.alive and server.loop.error is None
        for r in results:
            assert r["error"] is None, f"{r['id']}: {r['error']!r}"
            assert r["timeline"].first_chunk_s is not None and r["timeline"].first_chunk_s < 7.0, (
                f"{r['id']} first chunk at {r['timeline'].first_chunk_s} s ({report.summary()})"
            )


@pytest.mark.slow
def test_fleet_token_cannot_take_another_robots_identity(tmp_path):
    """Per-robot tokens are exclusive and a session is bound to the credential that made it."""
    tokens = {f"honest{k}": f"honest{k}-token-0123456789abcdef" for k in range(3)}
    fleet = "fleet-token-0123456789abcdef"
    path = tmp_path / "tokens"
    path.write_text(
        "\n".join([fleet, *(f"{r} {t}" for r, t in tokens.items()), "victim victim-token-0123456789abcdef", "reserved reserved-token-0123456789ab"])
        + "\n"
    )
    base = baseline("lookahead")
    with serving("lookahead", auth=AuthTokens.load(str(path))) as server:
        results, report = attack_while_honest_run(
            server, "identity", lead_s=1.0, honest={"tokens": tokens},
            fleet_token=fleet, protected_ids=("reserved", "honest0"), victim_id="victim",
            victim_token="victim-token-0123456789abcdef", other_token=tokens["honest1"], period_s=0.5,
        )  # fmt: skip
        assert report.extra.get("rounds", 0) >= 2, report.summary()
        assert_fleet_unharmed(server, results, base, report)


@pytest.mark.slow
@pytest.mark.parametrize("step_s", [3600.0, -3600.0])
def test_robot_whose_clock_steps_is_served_again(step_s):
    """One honest robot's clock jumps by an hour mid-run; once re-synchronised it must be served
    as before, and the others must not notice."""
    with serving("lookahead") as server:
        seconds, at = 5.0, 2.0
        clients = [honest_client(server.address, f"honest{k}", float(k + 1)) for k in range(3)]
        clients[0].clock = adv.SteppedClock(step_s, time.monotonic() + at)
        results = run_honest(server.address, seconds=seconds, clients=clients)
        assert server.loop.alive and server.loop.error is None
        stepped = results[0]["timeline"]
        before, after = stepped.starvation_pct(0.5, at), stepped.starvation_pct(at + 1.0)
        assert after is not None and before is not None
        assert after <= before + MARGIN_PP, f"after the step the robot starves {after:.1f}% (before {before:.1f}%)"
        others = [r["timeline"].starvation_pct(at) for r in results[1:]]
        assert max(others) <= MARGIN_PP, f"the other robots starved {others} after the step"


@pytest.mark.slow
@pytest.mark.subprocess
def test_idle_sockets_do_not_lock_out_robots():
    """1,100 TCP connections that never send a byte, then honest robots: in within seconds. The
    server starts with the usual soft limit of 1024 open files."""
    stop = threading.Event()
    report = adv.AttackReport("idle_sockets")
    with echo_server_process(nofile=1024) as (proc, address):
        thread = threading.Thread(target=adv.idle_sockets, args=(address, stop, STATE, report), daemon=True)
        thread.start()
        try:
            deadline = time.monotonic() + 10
            while report.counts["idle sockets connected"] + report.counts["socket connects failed"] < 1100 and time.monotonic() < deadline:
                time.sleep(0.05)
            results = run_honest(address, seconds=2.5)
        finally:
            stop.set()
            thread.join(timeout=20)
        assert report.counts["idle sockets connected"] >= 1000, report.summary()
        assert proc.poll() is None, "the server process died"
        for r in results:
            first = r["timeline"].first_chunk_s
            assert first is not None and first < 2.0, f"{r['id']}: first chunk at {first} s after 1,100 idle sockets ({report.summary()})"


@pytest.mark.slow
def test_garbage_and_jpeg_scan_bombs_do_not_hurt_the_fleet():
    """Bytes that are not protobuf on a registered stream, and progressive JPEGs of 200k scans."""
    base = baseline("lookahead", features=WITH_IMAGE)
    with serving("lookahead", features=WITH_IMAGE) as server:
        results, report = attack_while_honest_run(server, "garbage", features=WITH_IMAGE)
        garbage = sum(n for k, n in report.counts.items() if k.startswith("garbage:"))
        assert report.counts["scan bombs"] >= 3 and garbage >= 5, report.summary()
        assert_fleet_unharmed(server, results, base, report)


# ---- fuzz --------------------------------------------------------------------------------------

TIMES = (math.nan, math.inf, -math.inf, 1e308, -1e308, 1.7976931348623157e308, 5e-324, -5e-324, 0.0, -0.0, 1e18, -1e18, -1.0)
INTS = (0, 1, -1, 2**31 - 1, -(2**31), 2**62, adv.INT64_MAX, adv.INT64_MIN, 10**15)
DTYPES = ("float32", "float64", "uint8", "int64", "bool", "object", "", "V8")


def fuzz_time(rng: random.Random) -> float:
    now = time.monotonic()
    roll = rng.random()
    if roll < 0.4:
        return rng.choice(TIMES)
    if roll < 0.6:
        return adv.flip_bits(now, rng, rng.randint(1, 4))
    if roll < 0.8:
        return now + rng.uniform(-1e6, 1e6) * rng.choice((1e-6, 1e-3, 1.0))
    return now


def fuzz_int(rng: random.Random, near: int = 0) -> int:
    return rng.choice(INTS) if rng.random() < 0.5 else near + rng.randint(-3, 50)


def fuzz_tensors(rng: random.Random) -> list[pb.Tensor]:
    good = pb.Tensor(name="observation.state", dtype="float32", shape=[4], data=np.zeros(4, np.float32).tobytes())
    roll = rng.random()
    if roll < 0.5:
        return [good]
    bad = pb.Tensor()
    bad.CopyFrom(good)
    what = rng.randrange(6)
    if what == 0:
        bad.data = np.array([math.nan, math.inf, 1e38, -1e38], np.float32).tobytes()
    elif what == 1:
        bad.dtype = rng.choice(DTYPES)
    elif what == 2:
        bad.ClearField("shape")
        bad.shape.extend(rng.choice(([], [-1], [2, 2], [4, 0], [2**40], [1] * 12)))
    elif what == 3:
        bad.data = rng.randbytes(rng.randint(0, 40))
    elif what == 4:
        bad.encoding = rng.choice((1, 7))
    else:
        bad.name = rng.choice(("", "observation.other", "x" * 300, "observation.state\x00"))
    return [bad] if rng.random() < 0.7 else [good, bad]


def fuzz_message(rng: random.Random, index: int, chunk_ids: list[int]) -> pb.RobotMessage:
    kind = rng.random()
    if kind < 0.4:
        return pb.RobotMessage(observation=pb.Observation(index=fuzz_int(rng, index), capture_time=fuzz_time(rng), tensors=fuzz_tensors(rng)))
    if kind < 0.7:
        receipts = [
            pb.ChunkReceipt(chunk_id=rng.choice(chunk_ids) if chunk_ids and rng.random() < 0.5 else fuzz_int(rng), arrival_time=fuzz_time(rng), first_executed_index=fuzz_int(rng))
            for _ in range(rng.randint(0, 5))
        ]
        report = pb.ExecutionReport(
            report_time=fuzz_time(rng), index=fuzz_int(rng, index), executed_steps=fuzz_int(rng), starved_steps=fuzz_int(rng), chunks=receipts
        )
        return pb.RobotMessage(report=report)
    if kind < 0.97:
        sync = pb.ClockSync(**{f: fuzz_time(rng) for f in adv.CLOCK_FIELDS})
        if "sync_id" in pb.ClockSync.DESCRIPTOR.fields_by_name:
            sync.sync_id = fuzz_int(rng)
        return pb.RobotMessage(clock_sync=sync)
    return pb.RobotMessage()


REGISTRATION_VALUES = {
    "fps": (math.nan, math.inf, -math.inf, 0.0, -20.0, 1e308, 1e-308, 5e-324, 1e9, 20.0, 0.5, 999.0),
    "h_min": (-(2**31), -1, 0, 1, 2, 10, 11, 2**31 - 1),
    "h_max": (-(2**31), -1, 0, 1, 8, 10, 11, 2**31 - 1),
    "weight": (math.nan, math.inf, -1.0, 0.0, 5e-324, 1e-308, 1.0, 3.0, 1e308),
}


@pytest.mark.slow
def test_fuzz_5000_mutated_messages_then_an_honest_robot_is_served():
    """>= 5,000 mutated stream messages (times NaN/inf/huge/bit-flipped, random ints, clock
    syncs, reports, observations) from one robot that re-registers with mutated fps, horizons and
    weight whenever the server ends its session; afterwards an honest robot is served."""
    rng = random.Random(20261122)
    report = adv.AttackReport("fuzz")
    chunk_ids: list[int] = []
    robot: adv.Robot | None = None
    sent = registrations = 0
    deadline = time.monotonic() + 60.0
    with serving("lookahead", max_obs_rate_hz=0.0) as server:
        try:
            while sent < 5200:
                assert time.monotonic() < deadline, f"only {sent} messages in 60 s ({report.summary()})"
                if robot is None or robot.stream is None or not robot.stream.alive:
                    if robot is not None:
                        robot.close()
                    registrations += 1
                    robot = adv.Robot(server.address, STATE, report, f"fuzz{registrations % 3}", h_min=2, h_max=8)
                    mutated = {k: rng.choice(v) for k, v in REGISTRATION_VALUES.items() if rng.random() < 0.6}
                    if robot.register(**mutated) is None and robot.register() is None:
                        code = robot.error.code().name if robot.error is not None else "?"
                        assert code in ACCEPTABLE_REGISTER_CODES, f"a valid registration was answered {code}"
                        robot.close()
                        robot = None
                        time.sleep(0.05)
                        continue
                    robot.open(on_message=lambda m: chunk_ids.append(m.chunk.chunk_id) if m.WhichOneof("kind") == "chunk" else None)
                if robot.stream.send(fuzz_message(rng, sent, chunk_ids[-8:]), wait_s=2.0):
                    sent += 1
                    if sent % 500 == 0:
                        assert server.loop.alive and server.loop.error is None, f"serving loop died after {sent} messages: {server.loop.error!r}"
            time.sleep(0.5)
        finally:
            if robot is not None:
                robot.close()
        bad = {k: v for k, v in report.codes.items() if k.startswith("register") and k.split()[-1] not in ACCEPTABLE_REGISTER_CODES}
        assert not bad, f"registrations answered with server errors: {bad}"
        assert server.loop.alive and server.loop.error is None, f"serving loop died: {server.loop.error!r} ({report.summary()})"
        results = run_honest(server.address, n=1, seconds=2.0)
        assert results[0]["chunks"] > 0 and results[0]["timeline"].starvation_pct(0.5) < 50, (results[0], report.summary())
        assert not results[0]["wrong"], "the honest robot got the fuzzer's chunk"
    assert sent >= 5000 and registrations >= 1
