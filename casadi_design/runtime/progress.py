"""Progress bars for the long loops (multi-start, sweep, Monte Carlo): tqdm on stderr.

Bars show only on a terminal (``disable=None``) and never with ``quiet``; they leave no line
behind when done, so the printed tables stay readable.
"""

from __future__ import annotations

from typing import Any


def progress_bar(total: int, desc: str, quiet: bool = False, unit: str = "start") -> Any:
    """A ``tqdm`` bar of ``total`` steps; call ``.update(k)``, ``.set_postfix_str(s)``, ``.close()``."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=True if quiet else None, leave=False)
