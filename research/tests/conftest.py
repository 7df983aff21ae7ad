"""Put ``research/`` on ``sys.path`` so the study's tests can ``import armory_research``.

The study is not part of the installed package; run these tests with ``make research`` or
``.venv/bin/python -m pytest research/tests`` from the repository root (``make test`` does not
collect them: pyproject's ``testpaths`` is ``tests``).
"""

from __future__ import annotations

import sys
from pathlib import Path

RESEARCH = Path(__file__).resolve().parents[1]
if str(RESEARCH) not in sys.path:
    sys.path.insert(0, str(RESEARCH))
