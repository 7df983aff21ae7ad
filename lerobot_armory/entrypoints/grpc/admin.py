"""The operator's RPCs (``ArmoryAdmin``: swap the served checkpoint, status) on the robots' port.

Only the translation lives here: authentication by operator token, protobuf in and out. The
swap itself is the serving core's (:mod:`lerobot_armory.serving.swap`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import grpc

from lerobot_armory.entrypoints.grpc.hardening import Malformed
from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import ArmoryAdminServicer
from lerobot_armory.proto.limits import TOKEN_KEY
from lerobot_armory.serving.fleet import Fleet
from lerobot_armory.serving.peer_log import ThrottledLog
from lerobot_armory.serving.security import OperatorTokens
from lerobot_armory.serving.session import DEFAULT_POLICY
from lerobot_armory.serving.swap import PolicySwapper

log = logging.getLogger(__name__)

MAX_PATH = 4096
MAX_OVERRIDES = 64
NO_OPERATOR = "admin calls are off: the server was started without --operator_token_file"


def authorise(operators: OperatorTokens | None, context: grpc.ServicerContext, peer_log: ThrottledLog) -> None:
    """Abort the call unless it carries one of ``operators``' tokens (None: admin calls are off)."""
    if operators is None:
        context.abort(grpc.StatusCode.PERMISSION_DENIED, NO_OPERATOR)
    token = dict(context.invocation_metadata()).get(TOKEN_KEY, "")
    if not operators.check(token if isinstance(token, str) else ""):
        peer_log.warn(context.peer(), "admin call refused: missing or wrong operator token")
        context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or wrong operator token")


def check_swap_request(request: pb.SwapRequest, context: grpc.ServicerContext, served: tuple[str, ...] = (DEFAULT_POLICY,)) -> str:
    """Abort a malformed or oversized ``SwapRequest``, or one naming a policy not served; returns
    the name of the policy to swap ("" names the only one, or "default" the first of one)."""
    if isinstance(request, Malformed):
        context.abort(grpc.StatusCode.INVALID_ARGUMENT, "malformed SwapRequest")
    name = request.policy_name
    if not name and len(served) == 1:
        name = served[0]
    elif name == DEFAULT_POLICY and len(served) == 1:
        name = served[0]
    if name not in served:
        names = ", ".join(repr(n) for n in served)
        what = f"no policy named {request.policy_name[:80]!r}" if name else "this server serves several policies"
        context.abort(grpc.StatusCode.NOT_FOUND, f"{what}: it serves {names}; name one with --policy_name=NAME")
    if len(request.policy_path) > MAX_PATH or len(request.overrides) > MAX_OVERRIDES or any(len(o) > MAX_PATH for o in request.overrides):
        context.abort(grpc.StatusCode.INVALID_ARGUMENT, "policy path or overrides too long")
    return name


class AdminService(ArmoryAdminServicer):
    """``SwapPolicy`` and ``Status`` for holders of an operator token (none configured: refused)."""

    def __init__(
        self,
        swapper: PolicySwapper,
        fleet: Fleet,
        operators: OperatorTokens | None,
        status_line: Callable[[], str],
        swappers: dict[str, PolicySwapper] | None = None,
    ) -> None:
        self.swapper = swapper  # the first policy's
        self.swappers = swappers or {DEFAULT_POLICY: swapper}  # every policy's, by name
        self.fleet = fleet
        self.operators = operators
        self.status_line = status_line
        self.peer_log = ThrottledLog(log)

    def _authorise(self, context: grpc.ServicerContext) -> None:
        authorise(self.operators, context, self.peer_log)

    def SwapPolicy(self, request: pb.SwapRequest, context: grpc.ServicerContext) -> pb.SwapResponse:  # noqa: N802
        self._authorise(context)
        name = check_swap_request(request, context, tuple(self.swappers))
        log.info(
            "operator %s asks to swap policy %s to %s%s", context.peer(), name, request.policy_path, " (drain)" if request.drain else ""
        )
        result = self.swappers[name].swap(request.policy_path, list(request.overrides), request.drain)
        return pb.SwapResponse(
            result=result.result, message=result.message, old_path=result.old_path, new_path=result.new_path, seconds=result.seconds
        )

    def Status(self, request: pb.AdminStatusRequest, context: grpc.ServicerContext) -> pb.AdminStatusResponse:  # noqa: N802
        self._authorise(context)
        with self.fleet.cond:
            robots = len(self.fleet.active())
        counts = self.swapper.counts.by_result
        return pb.AdminStatusResponse(
            policy_path=self.swapper.current.path, policy=self.swapper.current.description, robots=robots,
            swaps_ok=counts["ok"], swaps_refused=counts["refused"], swaps_failed=counts["failed"], status_line=self.status_line(),
        )  # fmt: skip
