"""The server's binding of the generated ``Armory`` service, with request deserializers that never raise.

Robots use the generated client (``armory_pb2_grpc.ArmoryStub``) and the server's servicer
subclasses the generated ``ArmoryServicer``; only the server's registration is wrapped here,
because the generated ``add_ArmoryServicer_to_server`` parses requests with ``FromString``.
Measured with it (grpcio 1.85.1): one undecodable message on a robot's stream logs an ERROR
"Exception deserializing message!" with a 5-line traceback and ends that stream with
``INTERNAL "Exception deserializing request!"``, so the robot loses its session over one bad
message, and a robot sending garbage writes a traceback per message. And ``FromString`` parses a
16 MiB ``ExecutionReport`` of 8.4 M receipts whole, holding the GIL for seconds.

:func:`add_armory_to_server` therefore takes the generated method handlers and swaps in
:func:`safe_deserializer`: bytes that do not parse become a :class:`Malformed` the servicer
answers (one notice, one throttled log line, the stream goes on), and an oversized report is
refused before parsing (:data:`~lerobot_armory.proto.limits.MAX_REPORT_BYTES`). It also checks,
once when the servicer is bound, that the servicer implements every RPC, where the generated base
class would answer ``UNIMPLEMENTED`` per call.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import grpc
from google.protobuf import message_factory

from lerobot_armory.proto import armory_pb2 as pb
from lerobot_armory.proto.armory_pb2_grpc import (
    ArmoryAdminServicer,
    ArmoryServicer,
    add_ArmoryAdminServicer_to_server,
    add_ArmoryServicer_to_server,
)
from lerobot_armory.proto.limits import MAX_REPORT_BYTES

__all__ = [
    "MAX_ERROR_CHARS", "MAX_REPORT_BYTES", "Malformed", "add_admin_to_server", "add_armory_to_server", "rpc_names", "safe_deserializer",
]

# Longest parse error kept in a Malformed: the message of a DecodeError is short, anything longer is noise.
MAX_ERROR_CHARS = 200

# First byte of a RobotMessage whose first field is its ExecutionReport (field 2, length-delimited).
_REPORT_TAG = 0x12


@dataclass(frozen=True)
class Malformed:
    """What the server's deserializer hands the servicer in place of a request that does not parse.

    Attributes:
        error: why parsing failed (the parser's message, cut to :data:`MAX_ERROR_CHARS`).
        size: the request's length in bytes.
    """

    error: str
    size: int


def safe_deserializer(message_type: type) -> Callable[[bytes], Any]:
    """``message_type.FromString`` that returns a :class:`Malformed` instead of raising."""
    parse = message_type.FromString
    robot_message = message_type is pb.RobotMessage

    def deserialize(data: bytes) -> Any:
        if robot_message and len(data) > MAX_REPORT_BYTES and data[:1] == bytes((_REPORT_TAG,)):
            return Malformed(f"execution report of {len(data)} bytes refused (limit {MAX_REPORT_BYTES})", len(data))
        try:
            return parse(data)
        except Exception as exc:  # noqa: BLE001 - DecodeError or anything else: the bytes are the robot's fault
            return Malformed(f"{type(exc).__name__}: {exc}"[:MAX_ERROR_CHARS], len(data))

    deserialize.__name__ = f"safe_{message_type.__name__}_FromString"
    return deserialize


def rpc_names(base: type = ArmoryServicer) -> list[str]:
    """The RPCs of the generated servicer base, i.e. of the ``.proto``'s service."""
    return [name for name, value in vars(base).items() if not name.startswith("_") and callable(value)]


class _Recorder:
    """Stands in for a ``grpc.Server`` while the generated code registers: keeps its handler table."""

    def __init__(self) -> None:
        self.tables: dict[str, dict[str, grpc.RpcMethodHandler]] = {}

    def add_generic_rpc_handlers(self, generic_handlers: Any) -> None:
        pass  # the generated code hands the same table to add_registered_method_handlers

    def add_registered_method_handlers(self, service_name: str, method_handlers: dict[str, Any]) -> None:
        self.tables[service_name] = method_handlers


def add_armory_to_server(servicer: ArmoryServicer, server: grpc.Server) -> None:
    """Serve ``servicer``'s RPCs on ``server``, each request parsed by :func:`safe_deserializer`.

    The servicer receives a :class:`Malformed` for any request whose bytes do not parse.

    Raises:
        TypeError: ``servicer`` does not implement one of the service's RPCs (caught here, not per call).
    """
    _bind(servicer, server, ArmoryServicer, add_ArmoryServicer_to_server)


def add_admin_to_server(servicer: ArmoryAdminServicer, server: grpc.Server) -> None:
    """Serve the operator RPCs (``ArmoryAdmin``) as :func:`add_armory_to_server` serves the robots'."""
    _bind(servicer, server, ArmoryAdminServicer, add_ArmoryAdminServicer_to_server)


def _bind(servicer: Any, server: grpc.Server, base: type, add: Callable[[Any, Any], None]) -> None:
    for name in rpc_names(base):
        method = getattr(servicer, name, None)
        if not callable(method) or getattr(method, "__func__", method) is vars(base)[name]:
            raise TypeError(f"{type(servicer).__name__} does not implement the {base.__name__.removesuffix('Servicer')} RPC {name!r}")
    recorder = _Recorder()
    add(servicer, recorder)
    if not recorder.tables:  # pragma: no cover - only a grpcio-tools that registers differently
        raise RuntimeError(f"armory_pb2_grpc.{add.__name__} registered no method table")
    for service_name, generated in recorder.tables.items():
        methods = pb.DESCRIPTOR.pool.FindServiceByName(service_name).methods_by_name
        handlers = {}
        for name, handler in generated.items():
            request_type = message_factory.GetMessageClass(methods[name].input_type)
            handlers[name] = handler._replace(request_deserializer=safe_deserializer(request_type))
        server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(service_name, handlers),))
        # grpc also looks methods up in this per-service table, skipping the generic path matching per call
        server.add_registered_method_handlers(service_name, handlers)
