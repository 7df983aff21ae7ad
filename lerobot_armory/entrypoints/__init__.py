"""Entrypoints: each translates its wire to the serving core's messages at its edge.

- :mod:`.grpc`: the robot protocol (protobuf over gRPC), with its hardening;
- :mod:`.openpi`: openpi's websocket policy protocol;
- :mod:`.cluster`: a Ray cluster of servers behind one front;
- :mod:`.server`: ``lerobot-armory-server``, assembling the loop, the engine and the entrypoints;
- :mod:`.status`: ``lerobot-armory-status``.
"""
