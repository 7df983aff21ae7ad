"""Robot side: the client control loop, simulated robots and robot adapters."""
