"""Offline builders of LeRobot policy directories with random weights (demo, tests, benchmarks), one per kind."""
