"""Engine acceleration for LeRobot's π0 family and SmolVLA: static samplers a CUDA graph records
(one per policy type, chosen by ``static_sampler.py``), their fused layers and Triton kernels, RTC's
guidance shared with LeRobot's loop, and ``op_trace.py`` (what a forward pass asks of a device,
seen from a CPU). Model code: it knows no engine, robot, session or wire."""
