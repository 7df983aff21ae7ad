"""openpi clients, run in openpi-client's own environment (numpy < 2), as on a robot computer.

    python openpi_clients.py PORT OUT_DIR MODE N REQUESTS [DURATION_S] [PACE_S]

MODE:
- ``infer``: N concurrent ``WebsocketClientPolicy`` clients, REQUESTS ``infer`` calls each; client k
  saves its first observation and chunk to OUT_DIR/client{k}.npz and its latencies to a JSON.
- ``broker``: one ``ActionChunkBroker(WebsocketClientPolicy, action_horizon=5)``, REQUESTS steps.
- ``bad``: N - 1 good clients as in ``infer`` while one more sends garbage and a wrong observation.
- ``bench``: N clients calling ``infer`` for DURATION_S seconds, each waiting PACE_S after every
  reply (the time its robot takes to execute the chunk's first actions); latencies to JSON.
- ``staggered``: as ``infer``, each client waiting a random 0..PACE_S (seeded by k) after every
  reply, so that clients answered in one batch do not ask again in lockstep.

Only openpi_client, numpy and websockets are imported here: nothing of lerobot-armory.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

import numpy as np
from openpi_client import action_chunk_broker, websocket_client_policy

IMAGE = 32


def observation(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "observation/image": rng.integers(0, 255, size=(IMAGE, IMAGE, 3), dtype=np.uint8),
        "observation/state": rng.normal(size=(2,)),  # float64, cast by the server
        "prompt": "reach the target",
    }


def good_client(
    port: int,
    out: Path,
    k: int,
    requests: int,
    results: dict,
    duration_s: float = 0.0,
    pace_s: float = 0.0,
    stagger: bool = False,
) -> None:
    policy = websocket_client_policy.WebsocketClientPolicy(host="127.0.0.1", port=port)
    latencies = []
    rng = np.random.default_rng(k)
    first = None
    n = 0
    start = time.perf_counter()
    while (n < requests) if not duration_s else (time.perf_counter() - start < duration_s):
        obs = observation(1000 * k + n)
        t = time.perf_counter()
        reply = policy.infer(obs)
        latencies.append(time.perf_counter() - t)
        if first is None:
            first = (obs, reply["actions"])
        n += 1
        if pace_s:
            time.sleep(rng.uniform(0.0, pace_s) if stagger else pace_s)
    elapsed = time.perf_counter() - start
    assert first is not None
    np.savez(out / f"client{k}.npz", image=first[0]["observation/image"], state=first[0]["observation/state"], actions=first[1])
    results[k] = {"latencies_s": latencies, "elapsed_s": elapsed, "metadata": policy.get_server_metadata()}


def bad_client(port: int, results: dict) -> None:
    """Garbage bytes, then an observation of the wrong shape: each answered with an error, the
    connection still usable for a good request after."""
    from websockets.sync.client import connect

    errors = []
    with connect(f"ws://127.0.0.1:{port}", compression=None, max_size=None) as ws:
        ws.recv()  # metadata
        ws.send(b"\xc1\xc1 not msgpack")
        errors.append(ws.recv())
    policy = websocket_client_policy.WebsocketClientPolicy(host="127.0.0.1", port=port)
    try:
        policy.infer({"observation/image": np.zeros((5, 5, 3), np.uint8), "observation/state": np.zeros(2)})
    except RuntimeError as exc:
        errors.append(str(exc))
    reply = policy.infer(observation(7))  # the same connection serves the next good request
    results["bad"] = {"errors": errors, "then_served": list(reply["actions"].shape)}


def main() -> None:
    port, out, mode, n, requests = int(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
    duration_s = float(sys.argv[6]) if len(sys.argv) > 6 else 0.0
    pace_s = float(sys.argv[7]) if len(sys.argv) > 7 else 0.0
    out.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    if mode == "broker":
        inner = websocket_client_policy.WebsocketClientPolicy(host="127.0.0.1", port=port)
        calls = []
        original = inner.infer
        inner.infer = lambda obs: (calls.append(1), original(obs))[1]  # count the server round trips
        broker = action_chunk_broker.ActionChunkBroker(inner, action_horizon=5)
        shapes = [list(broker.infer(observation(s))["actions"].shape) for s in range(requests)]
        results["broker"] = {"steps": requests, "server_calls": len(calls), "action_shapes": shapes}
    else:
        threads = []
        good = n - 1 if mode == "bad" else n
        for k in range(good):
            args = (port, out, k, requests, results, duration_s if mode == "bench" else 0.0, pace_s, mode == "staggered")
            threads.append(threading.Thread(target=good_client, args=args))
        if mode == "bad":
            threads.append(threading.Thread(target=bad_client, args=(port, results)))
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    (out / "results.json").write_text(json.dumps({str(k): v for k, v in results.items()}))


if __name__ == "__main__":
    main()
