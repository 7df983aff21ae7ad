"""lerobot-armory: serve one LeRobot policy to a fleet of robots with batched inference.

The pieces, each in one place:

- :mod:`lerobot_armory.mirror`: the server-side chunk mirror and *the* transition (docs/spec.md §2).
- :mod:`lerobot_armory.inference_latency`: batched-inference latency profiles ``d_infer(b)``.
- :mod:`lerobot_armory.schedulers`: RR, EDF and Lookahead behind one registry (docs/spec.md §3).
- :mod:`lerobot_armory.sim`: the discrete-event fleet simulator that drives the same mirror and
  schedulers with simulated time.
"""

__version__ = "0.1.0"
