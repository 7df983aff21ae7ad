"""Every console script's main, in one place (``pyproject.toml``'s ``[project.scripts]`` names these).

Each module is a thin main over the package that does the work:

- ``lerobot-armory-server`` (``server.py`` -> ``lerobot_armory.entrypoints.server``): serve a policy to a fleet of robots (gRPC, optionally openpi).
- ``lerobot-armory-client`` (``client.py`` -> ``lerobot_armory.robot.cli``): run one robot against a server (any LeRobot robot, PiPER, armory_sim, MetaWorld).
- ``lerobot-armory-cluster`` (``cluster.py`` -> ``lerobot_armory.entrypoints.cluster.cli``): serve from a Ray cluster of replicas behind one front.
- ``lerobot-armory-admin`` (``admin.py`` -> ``lerobot_armory.entrypoints.admin``): the operator's client: swap a checkpoint, read a server's status.
- ``lerobot-armory-status`` (``status.py`` -> ``lerobot_armory.entrypoints.status``): a running server's fleet, one line per robot.
- ``lerobot-armory-bench`` (``bench.py`` -> ``lerobot_armory.bench.live``): the live server against the simulator's prediction, per scheduler.
- ``lerobot-armory-tasks`` (``tasks.py`` -> ``lerobot_armory.bench.tasks``): task success of a trained policy on MetaWorld: local, served, openpi.
- ``lerobot-armory-sim`` (``sim.py`` -> ``lerobot_armory.sim.cli``): one simulated fleet under one scheduler.
- ``lerobot-armory-sweep`` (``sweep.py`` -> ``lerobot_armory.sim.sweep``): the reference sweep in the simulator (CSV, JSON, figures).
- ``lerobot-armory-plan`` (``plan.py`` -> ``lerobot_armory.sim.plan``): capacity planning: how many GPUs a fleet needs.
- ``lerobot-armory-make-demo-policy`` (``make_demo_policy.py`` -> ``lerobot_armory.demo.build``): build a demo policy offline (random weights), loadable as --policy.path.
"""
