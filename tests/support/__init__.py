"""Test doubles and helpers the tests own (the benchmarks borrow some): the echo engine, adversarial robots."""
