"""The gRPC entrypoint: the robot protocol's service, and the hardening of its deserializers."""
