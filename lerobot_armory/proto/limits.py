"""Constants of the wire protocol that the server and the robot must agree on, defined once.

Written by hand (the ``.proto`` cannot hold them); the server (``entrypoints/grpc/service.py``), the robot
(``robot/connection.py``) and the server's request hardening (``entrypoints/grpc/hardening.py``) import them.
"""

from __future__ import annotations

# Full name of the service in armory.proto (package lerobot_armory.v1, service Armory): the path
# prefix of every RPC and the name the health service reports. tests/entrypoints/test_server.py checks it
# against the .proto's descriptor.
SERVICE_NAME = "lerobot_armory.v1.Armory"

# Stream metadata key that carries the session id Register handed out: the stream has no request
# message of its own to carry it, and the server must find the robot before reading its first message.
SESSION_KEY = "armory-session"

# Stream metadata key of the auth token (--auth_token_file): sent on every Stream as well as in
# RegisterRequest.auth_token, so that a session id alone does not open a stream.
TOKEN_KEY = "armory-token"

# Register metadata keys with which a cluster front names the robot host it forwards a registration
# for, and proves it (serving/forwarding.py): a replica holding the front's key counts the
# registration against that host; without a valid proof both are ignored.
FORWARDED_FOR_KEY = "x-armory-forwarded-for"
FORWARD_PROOF_KEY = "x-armory-forward-proof"

# Largest message either side sends or accepts unless told otherwise (the server's
# --max_message_mb, Connection(max_message_bytes=...)). An observation carries camera frames,
# raw unless the robot JPEG-encodes them: gRPC's own 4 MiB refuses a single raw 1080p RGB frame
# (6.2 MiB); 16 MiB holds two, and bounds what one message can make the other side buffer.
DEFAULT_MAX_MESSAGE_BYTES = 16 << 20

# A RobotMessage whose first field is an ExecutionReport larger than this is refused before
# parsing: the server reads at most 64 receipts (~2 KiB), and parsing a 16 MiB report of 8.4 M
# receipts held the GIL for seconds and cost ~400 MiB (honest robots starved 7-8 % in the
# adversarial bench).
MAX_REPORT_BYTES = 64 << 10

# HTTP/2 keepalive. A robot whose server's host vanished without closing the connection (power
# loss, a pod's node gone) would otherwise wait on a silent stream; pinging every KEEPALIVE_MS and
# giving up KEEPALIVE_TIMEOUT_MS later turns that into a broken stream (hold, re-register) within
# about 8 s. The server accepts pings that often (its default would answer them with GOAWAY).
KEEPALIVE_MS = 5000
KEEPALIVE_TIMEOUT_MS = 3000
CLIENT_KEEPALIVE_OPTIONS = (
    ("grpc.keepalive_time_ms", KEEPALIVE_MS),
    ("grpc.keepalive_timeout_ms", KEEPALIVE_TIMEOUT_MS),
    ("grpc.http2.max_pings_without_data", 0),
)
SERVER_KEEPALIVE_OPTIONS = (
    ("grpc.http2.min_recv_ping_interval_without_data_ms", KEEPALIVE_MS // 2),
    ("grpc.http2.max_ping_strikes", 0),
)
