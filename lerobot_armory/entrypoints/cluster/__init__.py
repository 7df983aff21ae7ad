"""One fleet across many GPUs and hosts: replicas of the server as Ray actors, and a front that places robots.

- :mod:`.replica`: one replica, the whole ``lerobot-armory-server`` (engine, mirrors, scheduler,
  its own gRPC port), as a plain class that Ray runs as an actor; the replica sets the front talks to.
- :mod:`.front`: the front service robots register with: it places each robot on a replica by
  the replicas' predicted load (:mod:`lerobot_armory.placement`), answers with that replica's
  address, follows the replicas' health, and moves robots between chunks to rebalance.
- :mod:`.cli`: ``lerobot-armory-cluster``.

Ray is an optional dependency (``pip install 'lerobot-armory[cluster]'``): only :mod:`.cli` and
:class:`.replica.RayReplicas` import it.
"""
