"""The replicas' per-host registration limit behind the cluster front, in one process: does a
flood from many hosts, each under the front's own per-host limit, spend a bucket every robot shares?

Two in-process replicas (the planner, default admission limits: 256 then 32 a second per host) and
the front; 8 flood hosts (10.0.0.0-7) send ``PER`` registrations each (fresh ids, never streamed)
through ``ClusterFront.Register`` with a stand-in gRPC context naming the host (one machine has no
8 addresses to register from; the front's forwarding to the replicas is real gRPC). Honest
newcomers from other hosts start ``DELAYS`` seconds into the flood and retry every 0.1 s until
admitted. Prints the flood's outcomes (``replica_rate``: refused by the replicas' limit) and each
newcomer's wait. Run it on any tree (its own classes only; the front's key is used where it has one):

    PYTHONPATH=. .venv/bin/python benchmarks/front_forwarded_hosts.py [PER=300] [DELAYS=12,16,20]
    PYTHONPATH=/path/to/before .venv/bin/python benchmarks/front_forwarded_hosts.py 300 12,16,20
"""

from __future__ import annotations

import collections
import logging
import sys
import tempfile
import threading
import time

import grpc

from lerobot_armory.entrypoints.cluster.front import ClusterFront, FrontOptions, FrontServer
from lerobot_armory.entrypoints.cluster.replica import ArmoryReplica, LocalReplicas
from lerobot_armory.proto import armory_pb2 as pb
from tests.support.cluster import IMAGE, make_planner, replica_config

FEATURES = {"observation.state": ("float32", (2,)), "observation.images.front": ("uint8", (IMAGE, IMAGE, 3))}
HOSTS = 8


class Refused(Exception):
    pass


class RobotAt:
    """What the front's Register reads of a gRPC context, for a robot at ``host``. Its own copy of
    ``tests/support/cluster.py``'s: this script also runs on trees that predate that one."""

    def __init__(self, host: str) -> None:
        self._peer = f"ipv4:{host}:40000"

    def peer(self) -> str:
        return self._peer

    def time_remaining(self) -> float:
        return 5.0

    def invocation_metadata(self) -> tuple:
        return ()

    def abort(self, code: grpc.StatusCode, details: str) -> None:
        raise Refused("replica_rate" if "through this front" in details else code.name)


def register(front: ClusterFront, host: str, robot_id: str) -> str:
    features = [pb.TensorSpec(name=n, dtype=d, shape=list(s)) for n, (d, s) in FEATURES.items()]
    request = pb.RegisterRequest(robot_id=robot_id, fps=20.0, h_min=1, h_max=10, weight=1.0, tier="slow", features=features)
    try:
        front.Register(request, RobotAt(host))
        return "OK"
    except Refused as exc:
        return str(exc)


def main(per: int, delays: tuple[float, ...]) -> None:
    logging.disable(logging.WARNING)
    planner = make_planner(tempfile.mkdtemp() + "/planner")
    replicas = {f"r{k}": ArmoryReplica(replica_config(planner), f"r{k}") for k in range(2)}
    server = FrontServer(ClusterFront(LocalReplicas(replicas), FrontOptions(health_interval_s=0.25)))
    front = server.front
    deadline = time.monotonic() + 10
    while not all(s.view.healthy and getattr(s, "keyed", True) for s in front.state.values()) and time.monotonic() < deadline:
        time.sleep(0.05)
    outcomes: collections.Counter[str] = collections.Counter()
    lock = threading.Lock()
    joins: dict[str, tuple[float, int]] = {}

    def flood(h: int) -> None:
        for k in range(per):
            answer = register(front, f"10.0.0.{h}", f"flood-{h}-{k}")
            with lock:
                outcomes[answer] += 1

    def newcomer(j: int, delay: float) -> None:
        time.sleep(delay)
        start, refused = time.monotonic(), 0
        while register(front, f"10.0.9.{j}", f"newcomer{j}-{refused}") != "OK":
            refused += 1
            time.sleep(0.1)
        joins[f"newcomer{j}"] = (round(time.monotonic() - start, 2), refused)

    t0 = time.monotonic()
    threads = [threading.Thread(target=flood, args=(h,)) for h in range(HOSTS)]
    threads += [threading.Thread(target=newcomer, args=(j, d)) for j, d in enumerate(delays)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    print(
        f"flood {HOSTS * per} from {HOSTS} hosts in {time.monotonic() - t0:.1f} s: {dict(outcomes)}; "
        f"newcomers (s to admission, refusals): {joins}; front refused {dict(front.refused)}"
    )
    server.stop(0)
    for replica in replicas.values():
        replica.stop()


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 300, tuple(float(x) for x in (sys.argv[2] if len(sys.argv) > 2 else "12,16,20").split(",")))
