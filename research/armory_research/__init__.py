"""The offline scheduling study (the frontier study): research code, not part of the installed package.

- :mod:`armory_research.optimal`: the exact best work-conserving schedule of a deterministic
  episode (branch-and-bound), :func:`~armory_research.optimal.play` (a scheduler on that episode
  through the real mirror), :class:`~armory_research.optimal.ReplayScheduler`;
- :mod:`armory_research.bound`: Lagrangian device-pricing upper bounds on any schedule;
- :mod:`armory_research.frontier`: the study itself (``python -m armory_research.frontier``);
- :mod:`armory_research.variants`: scheduler settings the study compares that the product does not
  offer (``rollout_same``), registered when this package is imported.

It imports the product (``lerobot_armory``); the product never imports it. Put ``research/`` on
``sys.path`` to use it (``PYTHONPATH=research``; ``research/tests/conftest.py`` and
``research/benchmarks/_study.py`` do it). See ``research/README.md``.
"""

from armory_research import variants  # noqa: E402,F401  (registers the study's scheduler variants)
