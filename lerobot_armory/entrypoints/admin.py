"""``lerobot-armory-admin``: the operator's calls to a running server, over its gRPC port.

    lerobot-armory-admin swap --address=gpu-box:8080 --operator_token_file=operator.txt \\
        --policy.path=outputs/act_v2 [--policy.<field>=value ...] [--drain=true] [--tls_ca=server.crt]
    lerobot-armory-admin status --address=gpu-box:8080 --operator_token_file=operator.txt

``swap`` loads the new checkpoint beside the served one, warms it up, checks that robots can keep
sending what they send, and switches between two batches (serving/swap.py). It prints one line:
what is served now, or why nothing changed; it exits 0 on success, 1 when the server refused or
failed the swap, 2 on a usage error, 3 when the call itself failed (unreachable, bad token).

``--address`` may be a cluster front (``lerobot-armory-cluster``): ``swap`` then rolls replica by
replica, stopping at the first that refuses or fails (the line says which replicas serve which
path), and ``status`` adds each replica's path and swaps.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field

import grpc

from lerobot_armory.cli_util import parse_or_exit, run_or_exit, split_passthrough
from lerobot_armory.errors import ConfigError
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import ArmoryAdminStub
from lerobot_armory.proto.limits import TOKEN_KEY
from lerobot_armory.robot.cli import read_ca, read_token
from lerobot_armory.robot.connection import open_channel

PROG = "lerobot-armory-admin"
COMMANDS = ("swap", "status")


@dataclass
class SwapTarget:
    """``--policy.path``: the checkpoint to serve (every other ``--policy.<field>`` is an override)."""

    path: str = ""
    overrides: list[str] = field(default_factory=list)


@dataclass
class AdminConfig:
    """Options of ``lerobot-armory-admin swap|status``.

    Attributes:
        address: the server's gRPC ``host:port``.
        operator_token_file: a file holding an operator token (the server's ``--operator_token_file``).
        tls_ca: PEM of the CA that signed the server's certificate (when the server speaks TLS).
        policy: ``--policy.path=DIR`` and ``--policy.<field>=value`` overrides (swap).
        drain: release the served policy before loading the new one (one in memory at a time;
            robots see a pause in service for the load and warm-up, not an error).
        timeout_s: how long to wait for the server's answer (a load and warm-up can take minutes).
        policy_name: which policy to swap on a server of several (``--policies``); empty: the only one.
    """

    address: str = "127.0.0.1:8080"
    operator_token_file: str | None = None
    tls_ca: str | None = None
    policy: SwapTarget = field(default_factory=SwapTarget)
    drain: bool = False
    timeout_s: float = 900.0
    policy_name: str = ""


def call(command: str, cfg: AdminConfig) -> tuple[int, str]:
    """Make one admin call; returns (exit code, the line to print)."""
    if command == "swap" and not cfg.policy.path:
        raise ConfigError("policy.path", "swap needs --policy.path=DIR (the checkpoint to serve)")
    token = read_token(cfg.operator_token_file, "operator_token_file")
    channel = open_channel(cfg.address, read_ca(cfg.tls_ca))
    stub = ArmoryAdminStub(channel)
    metadata = ((TOKEN_KEY, token),) if token else ()
    try:
        if command == "swap":
            request = pb.SwapRequest(
                policy_path=cfg.policy.path, overrides=cfg.policy.overrides, drain=cfg.drain, policy_name=cfg.policy_name
            )
            r = stub.SwapPolicy(request, timeout=cfg.timeout_s, metadata=metadata)
            if r.result == "ok":
                return 0, f"swapped {r.old_path} -> {r.new_path} in {r.seconds:.2f} s: {r.message}"
            return 1, f"swap {r.result}: {r.message}"
        s = stub.Status(pb.AdminStatusRequest(), timeout=cfg.timeout_s, metadata=metadata)
        line = (
            f"policy {s.policy_path} ({s.policy}); robots {s.robots}; swaps ok {s.swaps_ok}, refused {s.swaps_refused}, "
            f"failed {s.swaps_failed}; {s.status_line}"
        )
        for r in s.replicas:  # a cluster front: each replica's path and own swaps
            line += (
                f" | {r.replica_id} {'up' if r.up else 'DOWN'} {r.policy_path or '-'} robots {r.robots} "
                f"swaps ok {r.swaps_ok}, refused {r.swaps_refused}, failed {r.swaps_failed}"
            )
        return 0, line
    except grpc.RpcError as exc:
        return 3, f"{command} refused: {exc.code().name}: {exc.details()}"
    finally:
        channel.close()


def parse(argv: list[str] | None) -> tuple[str, AdminConfig]:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] not in COMMANDS:
        if args and args[0] in ("-h", "--help"):
            print(__doc__)
            sys.exit(0)
        print(f"{PROG}: error: the first argument must be one of {', '.join(COMMANDS)}", file=sys.stderr)
        sys.exit(2)
    command = args.pop(0)
    own = {"path", "overrides"}
    rest, overrides = split_passthrough(args, "policy", own)
    cfg = parse_or_exit(AdminConfig, rest, f"{PROG} {command}")
    cfg.policy.overrides = [*cfg.policy.overrides, *overrides]
    return command, cfg


def main(argv: list[str] | None = None) -> None:
    """Console entry point."""
    command, cfg = parse(argv)
    code, line = run_or_exit(lambda c: call(command, c), cfg, PROG)
    print(line, file=sys.stdout if code == 0 else sys.stderr)
    sys.exit(code)


if __name__ == "__main__":
    main()
