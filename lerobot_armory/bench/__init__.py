"""Live benchmark: the real server and a fleet of simulated robots over the real protocol."""
