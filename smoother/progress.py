"""Progress bars for long runs (tqdm), shown only on an interactive terminal unless asked."""
from __future__ import annotations

import sys

from tqdm import tqdm


def progress_bar(total: int, description: str, enabled: bool | None = None):
    """A tqdm bar; ``enabled=None`` shows it when stderr is a terminal."""
    if enabled is None:
        enabled = sys.stderr.isatty()
    return tqdm(total=total, desc=description, unit="step", disable=not enabled, leave=False,
                mininterval=0.5, dynamic_ncols=True)
