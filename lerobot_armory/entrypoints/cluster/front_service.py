"""The cluster front's gRPC face: ``Register`` asks the coordinator (:class:`~lerobot_armory.
entrypoints.cluster.front.ClusterFront`) where the robot should go, forwards the request there
unchanged (the replica checks features, tokens and the grant rules itself) and answers with the
replica's address; ``Stream`` is refused (robots stream to their replica). The coordinator keeps
the replicas' view, placement, moves and rolls; this class only translates the wire.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from typing import Protocol

import grpc

from lerobot_armory.entrypoints.grpc.hardening import Malformed
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import ArmoryServicer, ArmoryStub
from lerobot_armory.proto.limits import FORWARD_PROOF_KEY, FORWARDED_FOR_KEY
from lerobot_armory.serving.admission import AdmissionLimiter, peer_host
from lerobot_armory.serving.forwarding import ForwardingKey
from lerobot_armory.serving.peer_log import ThrottledLog

log = logging.getLogger("lerobot_armory.entrypoints.cluster.front")

# Answers from a replica that mean "try another replica" rather than "the robot is wrong" (UNKNOWN
# and INTERNAL: the replica broke while answering; the robot would otherwise give up).
TRY_ANOTHER = (
    grpc.StatusCode.UNAVAILABLE,
    grpc.StatusCode.DEADLINE_EXCEEDED,
    grpc.StatusCode.RESOURCE_EXHAUSTED,
    grpc.StatusCode.UNKNOWN,
    grpc.StatusCode.INTERNAL,
)
# Of those, the answers after which the replica counts as down until its next health check.
DOWN = (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED)
# What a replica's refusal says when its registration limit refused (serving/admission.py): per
# robot host (the one the front proves) or per credential.
REPLICA_RATE = "too many registrations from"


class Coordinator(Protocol):
    """What the servicer asks of the coordinator (``front.ClusterFront``): the narrow channel
    between the wire and placement."""

    admission: AdmissionLimiter
    forwarding: ForwardingKey
    options: object  # FrontOptions: call_timeout_s

    def choices(self, request: pb.RegisterRequest) -> Iterator[str]: ...
    def reserve_for(self, rid: str, request: pb.RegisterRequest) -> tuple[str, bool]: ...
    def unreserve(self, rid: str, robot_id: str) -> None: ...
    def mark_down(self, rid: str) -> None: ...
    def placed_on(self, rid: str, robot_id: str) -> None: ...
    def refused_for(self, why: str) -> None: ...
    def stub(self, address: str) -> ArmoryStub: ...


class FrontService(ArmoryServicer):
    """``Register`` places (the coordinator decides) and forwards; ``Stream`` is refused."""

    def __init__(self, front: Coordinator) -> None:
        self.front = front
        self.peer_log = ThrottledLog(log)  # one line per misbehaving peer per 10 s

    def Register(self, request: pb.RegisterRequest, context: grpc.ServicerContext) -> pb.RegisterResponse:  # noqa: N802
        front = self.front
        if isinstance(request, Malformed):
            self.peer_log.warn(context.peer(), f"malformed RegisterRequest ({request.size} bytes): {request.error}")
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "malformed RegisterRequest")
        host = peer_host(context.peer())
        refused = front.admission.check(host)
        if refused is not None:
            self._refuse(context, grpc.StatusCode.RESOURCE_EXHAUSTED, "rate", refused)
        answers: list[tuple[str, grpc.StatusCode, str]] = []  # (replica, code, details) of the replicas that said no
        for rid in front.choices(request):
            address, keyed = front.reserve_for(rid, request)
            if not address:
                continue
            remaining = context.time_remaining()
            limit: float = front.options.call_timeout_s  # type: ignore[attr-defined]
            timeout = limit if remaining is None else max(0.05, min(limit, remaining))
            try:
                metadata = self._forwarded_for(host, request.robot_id) if keyed else None
                response = front.stub(address).Register(request, timeout=timeout, metadata=metadata)
            except grpc.RpcError as exc:
                front.unreserve(rid, request.robot_id)
                if exc.code() in TRY_ANOTHER:
                    answers.append((rid, exc.code(), exc.details() or ""))
                    if exc.code() in DOWN:
                        front.mark_down(rid)
                    continue
                context.abort(exc.code(), exc.details() or exc.code().name)  # the robot's own problem: told as is
            response.stream_address = address
            front.placed_on(rid, request.robot_id)
            log.info("placed %s on %s (%s)", request.robot_id, rid, address)
            return response
        if answers and all(code == grpc.StatusCode.RESOURCE_EXHAUSTED for _, code, _ in answers):
            what = "; ".join(f"{rid}: {details}" for rid, _, details in answers)
            if any(REPLICA_RATE in details for _, _, details in answers):
                # A replica's own registration limit refused: per robot host (the front's limit
                # lets that host through), per credential, or per this front's host on a replica
                # that did not take the forwarding key.
                self._refuse(
                    context, grpc.StatusCode.RESOURCE_EXHAUSTED, "replica_rate",
                    f"the replicas take no more registrations through this front for now ({what})",
                )  # fmt: skip
            self._refuse(context, grpc.StatusCode.RESOURCE_EXHAUSTED, "full", f"every replica is full of robots that ask ({what}); retry later")
        if answers:
            what = "; ".join(f"{rid}: {code.name}: {details}" for rid, code, details in answers)
            self._refuse(context, grpc.StatusCode.UNAVAILABLE, "unavailable", f"no replica could take this robot now ({what}); retry")
        self._refuse(context, grpc.StatusCode.UNAVAILABLE, "down", "no replica is up; retry")

    def _forwarded_for(self, host: str, robot_id: str) -> tuple[tuple[str, str], ...]:
        """The metadata naming the robot's host to a keyed replica, with its proof."""
        return ((FORWARDED_FOR_KEY, host), (FORWARD_PROOF_KEY, self.front.forwarding.proof(host, robot_id)))

    def _refuse(self, context: grpc.ServicerContext, code: grpc.StatusCode, why: str, message: str) -> None:
        """Refuse a registration: counted by reason, logged once per peer (per 10 s), told as it is."""
        self.front.refused_for(why)
        self.peer_log.warn(context.peer(), f"registration refused: {message}")
        context.abort(code, message)

    def Stream(self, request_iterator: Iterator[pb.RobotMessage], context: grpc.ServicerContext) -> Iterator[pb.ServerMessage]:  # noqa: N802
        context.abort(
            grpc.StatusCode.FAILED_PRECONDITION,
            "this is a lerobot-armory cluster front: register here, then stream to the replica named in "
            "RegisterResponse.stream_address (lerobot-armory's client follows it)",
        )
        yield from ()  # pragma: no cover - abort raises
