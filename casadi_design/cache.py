"""What the package keeps on disk between runs, per machine: the compiled CasADi functions
(:mod:`casadi_design.compiled`) and the capsules fitted around a robot's meshes
(:func:`casadi_design.collision.capsules_from_geometry`).

Everything kept is named by a hash of all it is computed from (the inputs' bytes and the code
that computes it), so a cached value is the value that would be computed, to the bit, and a
change of input or code computes anew. Files are written to a temporary name and renamed: a
killed run leaves no half-written file, and a file that cannot be read or written is computed
again (the cache only saves time).

Environment: ``CASADI_DESIGN_CACHE`` (the directory; default ``$XDG_CACHE_HOME/casadi_design``
or ``~/.cache/casadi_design``).
"""

from __future__ import annotations

import hashlib
import os
import pickle
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


def cache_dir() -> Path:
    """The directory of what is kept."""
    if os.environ.get("CASADI_DESIGN_CACHE"):
        return Path(os.environ["CASADI_DESIGN_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "casadi_design"


def digest(*parts: bytes) -> str:
    """A name for what is computed from ``parts`` (sha256, 32 hex digits)."""
    h = hashlib.sha256()
    for part in parts:
        h.update(len(part).to_bytes(8, "little"))
        h.update(part)
    return h.hexdigest()[:32]


def stored(kind: str, key: str, make: Callable[[], T]) -> T:
    """The value ``make()`` kept as ``<kind>-<key>.pickle`` (``key``: :func:`digest` of all it
    is computed from): read when it is there, else computed and written."""
    path = cache_dir() / f"{kind}-{key}.pickle"
    try:
        return pickle.loads(path.read_bytes())
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ImportError):
        pass
    value = make()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{kind}-", delete=False) as f:
            f.write(pickle.dumps(value))
        os.replace(f.name, path)
    except OSError:
        pass
    return value
