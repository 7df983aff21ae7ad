"""The engine: a loaded LeRobot policy run batched (loading, the batched forward, CUDA graphs, RTC, warm-up, profiling, latency emulation).

It knows nothing of robots, sessions or wires: the serving core hands it observations and gets chunks back.
"""
