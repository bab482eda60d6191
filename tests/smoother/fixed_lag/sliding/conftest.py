"""The sliding window's tests: ``banded_cases.py``, their shared block-banded matrices, sits next to
this file; keep it importable under --import-mode=importlib as under the default mode."""
from __future__ import annotations

import os
import sys

_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)
