"""What the package keeps: in this process, the values used last (:class:`Memo`: built problems,
cells, functions per model, approximate designs; :func:`memoised` functions: the fitted capsules
of a URDF, mesh clearances, mapped CasADi functions, the identification's Jacobians); on disk between runs, per machine, the compiled CasADi functions
(:mod:`casadi_design.robot.compiled`), the capsules fitted around a robot's meshes
(:func:`casadi_design.cell.collision.capsules_from_geometry`), the cell's pairs, the approximate
designs behind the bounds (:func:`casadi_design.execution.campaign.approximate_designs`) and the designs'
starts (:func:`casadi_design.optimisation.solve.solve_start`).

Everything kept is named by a hash of all it is computed from (the inputs' bytes and the code
that computes it), so a cached value is the value that would be computed, to the bit, and a
change of input or code computes anew. Files are written to a temporary name and renamed: a
killed run leaves no half-written file, and a file that cannot be read or written is computed
again (the cache only saves time).

Environment: ``CASADI_DESIGN_CACHE`` (the directory; default ``$XDG_CACHE_HOME/casadi_design``
or ``~/.cache/casadi_design``); ``CASADI_DESIGN_KEEP_DESIGNS`` (0: the approximate designs and
the designs' starts are computed in every run, not kept, :func:`keeping_designs`).
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import os
import pickle
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Generic, TypeVar

T = TypeVar("T")


#: 0: the approximate designs (:func:`casadi_design.execution.campaign.approximate_designs`) and the
#: designs' starts (:func:`casadi_design.optimisation.solve.solve_start`) are neither read from nor written to
#: the disk (the test suite: each test computes its own).
KEEP_DESIGNS = "CASADI_DESIGN_KEEP_DESIGNS"


def keeping_designs() -> bool:
    """Whether approximate designs and starts are kept on disk (:data:`KEEP_DESIGNS`)."""
    return os.environ.get(KEEP_DESIGNS, "1") != "0"


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
    is computed from): read when it is there, else computed and written. Processes that ask for
    the same value at once compute it once: the first holds a lock on ``<kind>-<key>.lock``
    while it computes, the others wait for it and read (the test workers or a command's worker
    processes on a fresh machine: the UR10's capsules take 3 s to fit)."""
    value = read(kind, key)
    if value is not None:
        return value
    try:
        cache_dir().mkdir(parents=True, exist_ok=True)
        lock = open(cache_dir() / f"{kind}-{key}.lock", "w")
    except OSError:  # no lock where nothing can be written: compute here
        lock = None
    try:
        if lock is not None:
            fcntl.flock(lock, fcntl.LOCK_EX)
            value = read(kind, key)  # computed by the process that held the lock
        if value is None:
            value = make()
            write(kind, key, value)
    finally:
        if lock is not None:
            lock.close()
    return value


def read(kind: str, key: str) -> object | None:
    """The value kept as ``<kind>-<key>.pickle``, or None when there is none to read."""
    try:
        return pickle.loads((cache_dir() / f"{kind}-{key}.pickle").read_bytes())
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ImportError):
        return None


def write(kind: str, key: str, value: object) -> None:
    """Keep ``value`` as ``<kind>-<key>.pickle`` (to a temporary name, then renamed; a file
    that cannot be written is left out)."""
    path = cache_dir() / f"{kind}-{key}.pickle"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{kind}-", delete=False) as f:
            f.write(pickle.dumps(value))
        os.replace(f.name, path)
    except OSError:
        pass


@functools.cache
def code_digest() -> str:
    """A name for this package's code and the libraries it computes with: every source file of
    the package and the versions of numpy, scipy, CasADi and Pinocchio (:func:`digest`)."""
    import casadi
    import numpy
    import pinocchio
    import scipy

    root = Path(__file__).parents[1]  # the package, every subpackage with it
    files = sorted(root.rglob("*.py"))
    sources = (part for f in files for part in (str(f.relative_to(root)).encode(), f.read_bytes()))
    versions = (numpy.__version__, scipy.__version__, casadi.__version__, pinocchio.__version__)
    return digest(*sources, *(v.encode() for v in versions))


#: What :meth:`Memo._find` returns for a key it has no value of.
_MISSING = object()


class Memo(Generic[T]):
    """The values of a pure function used last: at most ``size`` in this process (the least
    recently used dropped), and with ``kind`` also on disk as ``<kind>-<key>.pickle``
    (:func:`read`, :func:`write`) while ``disk()`` is true. A disk key is a :func:`digest` of all
    the value is computed from, so the value read back is the value that would be computed, to
    the bit; ``on_read`` marks a value read from the disk (e.g. to count what was kept). Threads
    may share a memo (a value may then be computed twice, never mixed up)."""

    def __init__(self, size: int, kind: str | None = None, disk: Callable[[], bool] = keeping_designs,
                 on_read: Callable[[T], T] | None = None):
        self.size, self.kind, self.disk, self.on_read = size, kind, disk, on_read
        self._values: OrderedDict[Hashable, T] = OrderedDict()
        self._lock = threading.Lock()

    def lookup(self, key: Hashable) -> T | None:
        """The value of ``key`` in this process or on disk, or None."""
        value = self._find(key)
        return None if value is _MISSING else value

    def _find(self, key: Hashable) -> object:
        """The value of ``key`` (None too, as a value), or ``_MISSING``."""
        with self._lock:
            if key in self._values:
                self._values.move_to_end(key)
                return self._values[key]
        if self.kind is not None and self.disk():
            value = read(self.kind, str(key))
            if value is not None:
                value = value if self.on_read is None else self.on_read(value)
                self._remember(key, value)
                return value
        return _MISSING

    def keep(self, key: Hashable, value: T) -> None:
        """Keep ``value`` as the value of ``key`` (in this process, and on disk with ``kind``)."""
        self._remember(key, value)
        if self.kind is not None and self.disk():
            write(self.kind, str(key), value)

    def get(self, key: Hashable, make: Callable[[], T]) -> T:
        """The value of ``key``: kept, or ``make()`` computed and kept (None is a value too)."""
        value = self._find(key)
        if value is _MISSING:
            value = make()
            self.keep(key, value)
        return value

    def clear(self) -> None:
        """Forget what this process keeps (the disk layer stays)."""
        with self._lock:
            self._values.clear()

    def empty(self) -> Memo[T]:
        """A memo like this one that keeps nothing yet (a test's fresh process)."""
        return Memo(self.size, self.kind, self.disk, self.on_read)

    def __len__(self) -> int:
        return len(self._values)

    def _remember(self, key: Hashable, value: T) -> None:
        if self.size <= 0:
            return
        with self._lock:
            self._values[key] = value
            self._values.move_to_end(key)
            while len(self._values) > self.size:
                self._values.popitem(last=False)


def memoised(size: int, key: Callable[..., Hashable] | None = None) -> Callable[[Callable[..., T]], Callable[..., T]]:
    """A decorator: the function's values by its (hashable, positional) arguments, or by
    ``key(*args)`` (what the value depends on), the ``size`` used last kept in this process (a
    :class:`Memo` without a disk layer, ``f.memo``)."""

    def decorate(f: Callable[..., T]) -> Callable[..., T]:
        memo: Memo[T] = Memo(size)

        @functools.wraps(f)
        def cached(*args: Hashable) -> T:
            return memo.get(args if key is None else key(*args), lambda: f(*args))

        cached.memo = memo  # type: ignore[attr-defined]
        return cached

    return decorate
