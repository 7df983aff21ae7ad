"""Admission in the serving core: registration limits per peer and credential, the proofs with
which a cluster front names a forwarded robot's host, and a full fleet's slot going to a newcomer
rather than to a robot that has stopped asking."""

from __future__ import annotations

import pickle

import pytest

from lerobot_armory.robot_spec import RobotSpec
from lerobot_armory.serving.admission import AdmissionLimiter, peer_host
from lerobot_armory.serving.fleet import Fleet, FleetError
from lerobot_armory.serving.forwarding import ForwardingKey
from lerobot_armory.serving.messages import Notice, NoticeKind


def test_a_peer_gets_its_burst_then_its_rate_and_other_peers_are_not_held_back():
    now = [0.0]
    limiter = AdmissionLimiter(peer_rate_hz=2.0, peer_burst=5, clock=lambda: now[0])
    assert [limiter.check("10.0.0.1") for _ in range(5)] == [None] * 5
    refused = limiter.check("10.0.0.1")
    assert refused is not None and "too many registrations from this host (10.0.0.1)" in refused
    assert limiter.check("10.0.0.2") is None  # another host has its own bucket
    now[0] = 1.0  # two tokens back
    assert limiter.check("10.0.0.1") is None and limiter.check("10.0.0.1") is None and limiter.check("10.0.0.1") is not None
    assert limiter.refused == 2


def test_a_credential_is_limited_across_hosts():
    limiter = AdmissionLimiter(peer_burst=100, credential_rate_hz=0.001, credential_burst=3, clock=lambda: 0.0)
    assert [limiter.check(f"10.0.0.{k}", b"token-a") for k in range(3)] == [None] * 3
    assert "this credential" in limiter.check("10.0.0.9", b"token-a")
    assert limiter.check("10.0.0.9", b"token-b") is None


def test_the_limiter_keeps_bounded_memory_however_many_peers_come():
    limiter = AdmissionLimiter(max_keys=8, clock=lambda: 0.0)
    for k in range(1000):
        limiter.check(f"10.0.{k // 256}.{k % 256}")
    assert len(limiter._buckets) == 8


@pytest.mark.parametrize(
    "peer,host", [("ipv4:127.0.0.1:5555", "127.0.0.1"), ("ipv6:[::1]:5555", "[::1]"), ("unix:/tmp/s", "unix:/tmp/s"), ("10.1.2.3", "10.1.2.3")]
)
def test_the_host_of_a_peer_drops_the_port(peer, host):
    assert peer_host(peer) == host


def _streaming(fleet: Fleet, robot_id: str):
    session = fleet.register(RobotSpec(robot_id, 20.0, 10, 1, 10), "", {})
    fleet.attach(session.session_id)
    return session


def test_a_forwarding_proof_holds_for_its_host_and_robot_only_and_hides_its_key():
    secret = bytes(range(32))
    key = ForwardingKey(secret)
    proof = key.proof("10.0.0.1", "arm-1")
    assert key.verify("10.0.0.1", "arm-1", proof)
    assert not key.verify("10.0.0.2", "arm-1", proof) and not key.verify("10.0.0.1", "arm-2", proof)
    assert not key.verify("10.0.0.1", "arm-1", ForwardingKey(bytes(32)).proof("10.0.0.1", "arm-1"))
    # host and robot id cannot trade characters: "10.0.0.1" + "2x" is not "10.0.0.12" + "x"
    assert key.proof("10.0.0.1", "2x") != key.proof("10.0.0.12", "x")
    for forged in ("", "zz", "é" * 64, proof.upper(), proof + "0"):  # garbage is refused, never raises
        assert not key.verify("10.0.0.1", "arm-1", forged)
    assert secret.hex() not in repr(key) and secret.hex() not in str(key)
    again = pickle.loads(pickle.dumps(key))  # how Ray hands it to a replica
    assert again.verify("10.0.0.1", "arm-1", proof)
    with pytest.raises(ValueError):
        ForwardingKey(b"short")
    assert ForwardingKey.generate().proof("h", "r") != ForwardingKey.generate().proof("h", "r")


def test_a_full_fleet_gives_the_slot_of_a_robot_that_stopped_asking_to_a_newcomer():
    now = [0.0]
    fleet = Fleet(lambda: now[0], max_robots=2, idle_session_s=10.0)
    quiet = _streaming(fleet, "quiet")
    busy = _streaming(fleet, "busy")
    now[0] = 5.0
    with pytest.raises(FleetError) as info:  # nobody idle long enough yet
        fleet.register(RobotSpec("new", 20.0, 10, 1, 10), "", {})
    assert info.value.code == "RESOURCE_EXHAUSTED"
    now[0] = 11.5
    fleet.on_observation(busy, 0, 11.0, {}, 11.4)  # busy asks; quiet has sent nothing for 11.5 s
    newcomer = fleet.register(RobotSpec("new", 20.0, 10, 1, 10), "", {})
    assert quiet.session_id not in fleet.sessions and {busy.session_id, newcomer.session_id} <= set(fleet.sessions)
    told = quiet.outbox.get(timeout=0)
    assert isinstance(told, Notice) and told.kind is NoticeKind.DROPPED and "sent no observation for 12 s" in told.message
    assert fleet.evicted_idle == 1


def test_a_robot_whose_batch_is_running_keeps_its_slot():
    now = [0.0]
    fleet = Fleet(lambda: now[0], max_robots=1, idle_session_s=1.0)
    only = _streaming(fleet, "only")
    fleet.in_flight = {only.session_id}
    now[0] = 50.0
    with pytest.raises(FleetError):
        fleet.register(RobotSpec("new", 20.0, 10, 1, 10), "", {})
    assert only.session_id in fleet.sessions
