"""The operator's RPCs on a cluster front (``ArmoryAdmin``, as on a single server).

``SwapPolicy`` rolls the swap of one policy replica by replica (:meth:`ClusterFront.roll`; on a
cluster of several policies the request names one, as on a single server); ``Status`` reports the
cluster's policy, its rolls by result and, per replica, the path it serves and its own swaps. With
several policies, ``policy`` lists the cluster's as ``name=path, ...`` and the status line each
replica's (``policy_path`` stays the main policy's).
Same operator tokens (``--operator_token_file``) as the replicas; none configured: refused.
"""

from __future__ import annotations

import logging
from typing import Any

import grpc

from lerobot_armory.entrypoints.grpc.admin import authorise, check_swap_request
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import ArmoryAdminServicer
from lerobot_armory.serving.peer_log import ThrottledLog
from lerobot_armory.serving.security import OperatorTokens

log = logging.getLogger(__name__)


class FrontAdminService(ArmoryAdminServicer):
    """``SwapPolicy`` (a rolling swap) and ``Status`` for holders of an operator token."""

    def __init__(self, front: Any, operators: OperatorTokens | None) -> None:
        """``front``: the :class:`~lerobot_armory.entrypoints.cluster.front.ClusterFront` (not imported: it imports this)."""
        self.front = front
        self.operators = operators
        self.peer_log = ThrottledLog(log)

    def SwapPolicy(self, request: pb.SwapRequest, context: grpc.ServicerContext) -> pb.SwapResponse:  # noqa: N802
        authorise(self.operators, context, self.peer_log)
        name = check_swap_request(request, context, self.front.policy_names())
        log.info(
            "operator %s asks to roll the cluster's policy %s to %s%s", context.peer(), name, request.policy_path,
            " (drain)" if request.drain else "",
        )  # fmt: skip
        remaining = context.time_remaining()
        timeout = 900.0 if remaining is None else max(1.0, remaining)
        r = self.front.roll(request.policy_path, list(request.overrides), request.drain, timeout, policy_name=name)
        return pb.SwapResponse(result=r.result, message=r.message, old_path=r.old_path, new_path=r.new_path, seconds=r.seconds)

    def Status(self, request: pb.AdminStatusRequest, context: grpc.ServicerContext) -> pb.AdminStatusResponse:  # noqa: N802
        authorise(self.operators, context, self.peer_log)
        front = self.front
        with front.lock:
            replicas = [
                pb.ReplicaStatus(
                    replica_id=rid, up=s.view.healthy, policy_path=s.policy[0] if s.policy else "", robots=len(s.reported),
                    swaps_ok=s.swaps.get("ok", 0), swaps_refused=s.swaps.get("refused", 0), swaps_failed=s.swaps.get("failed", 0),
                )  # fmt: skip
                for rid, s in sorted(front.state.items())
            ]
            rolls = dict(front.rolls)
            names = front.policy_names()
            paths = {name: front.cluster_path(name) for name in names}
            known = all(name in front.policies for name in names)
            served = {rid: dict(s.served) for rid, s in sorted(front.state.items())}
        up = sum(r.up for r in replicas)
        line = f"cluster front: {up}/{len(replicas)} replicas up"
        if len(names) > 1:  # ReplicaStatus has room for one path: the others are told here
            policy = "cluster policies: " + ", ".join(f"{name}={paths[name]}" for name in names)
            line += "".join(
                f"; {rid} serves " + ", ".join(f"{name}={path}" for name, (path, _) in policies.items())
                for rid, policies in served.items() if policies
            )  # fmt: skip
        else:
            policy = "cluster policy"
        return pb.AdminStatusResponse(
            policy_path=paths[names[0]], policy=policy if known else f"{policy} not known yet",
            robots=sum(r.robots for r in replicas), swaps_ok=rolls["ok"], swaps_refused=rolls["refused"],
            swaps_failed=rolls["failed"], status_line=line, replicas=replicas,
        )  # fmt: skip
