"""Test doubles and helpers the tests own (the benchmarks borrow some): the echo engine, the load generator,
adversarial robots, the Pusher robot double, mirrors in hand-chosen states, VLA and cluster helpers, a fake
PiPER arm, and openpi-client's own environment with its clients."""
