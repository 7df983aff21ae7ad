"""The serving core: the fleet of robot sessions, the serving loop, grant rules, security and metrics.

It speaks its own plain message types (:mod:`.messages`), never a wire format: each entrypoint translates at its edge.
"""
