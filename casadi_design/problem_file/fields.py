"""Reading one table of a problem file: typed access whose errors name the file, the table and
the key (:class:`TableReader`), and the limits every section shares (sizes, loads)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import ProblemError

#: Components of a twist (measured / required rows) and of a wrench, in the order used everywhere.
TWIST_ROWS = ("x", "y", "z", "rx", "ry", "rz")
WRENCH_ROWS = ("fx", "fy", "fz", "mx", "my", "mz")
#: Largest number of test poses and of experiments accepted. Each experiment adds a copy of the
#: symbolic B(q, F) to the NLP graph (about ``BYTES_PER_EXPERIMENT_L2`` L^2 bytes) and each test
#: pose an epigraph constraint (about ``BYTES_PER_TEST_POSE_L2`` L^2 bytes).
MAX_TEST_POSES = 5_000
MAX_EXPERIMENTS = 500
BYTES_PER_EXPERIMENT_L2 = 160_000
BYTES_PER_TEST_POSE_L2 = 4_000
MAX_LOAD_N = 1e6

Vec = tuple[float, ...]
Mat = tuple[tuple[float, ...], ...]


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


class TableReader:
    """Typed access to one TOML table with file/field-qualified errors."""

    def __init__(self, path: str, table: dict, section: str, sections: dict[str, set[str] | None],
                 label: str | None = None):
        """``section`` names the keys allowed (its entry of ``sections``: every section's
        ``KEYS``, :data:`casadi_design.problem_file.read.SECTIONS`); ``label`` names the table in
        messages (default ``section``: e.g. ``robot.dh.joints[3]`` for a row)."""
        self.path, self.table, self.section, self.sections = path, table, label or section, sections
        allowed = sections[section]
        unknown = sorted(set(table) - allowed) if allowed is not None else []
        if unknown:
            raise self.error(f"unknown key '{unknown[0]}'", f"allowed: {', '.join(sorted(allowed))}")

    def where(self, key: str | None = None) -> str:
        if not self.section:
            return f"{self.path}: {key or 'top level'}"
        return f"{self.path}: [{self.section}]" + (f".{key}" if key else "")

    def error(self, what: str, hint: str, key: str | None = None) -> ProblemError:
        return ProblemError(f"{self.where(key)}: {what}; {hint or 'fix it'}")

    def get(self, key: str, kind: type | tuple, default: Any = ..., hint: str = "") -> Any:
        """The value of ``key``, of type ``kind`` (an int is accepted for float); floats must
        be finite."""
        if key not in self.table:
            if default is ...:
                raise self.error("missing", hint or f"add {key} = ...", key)
            return default
        value = self.table[key]
        if kind is float and _is_number(value):
            value = float(value)
        if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
            name = kind.__name__ if isinstance(kind, type) else "/".join(k.__name__ for k in kind)
            raise self.error(f"expected {name}, got {value!r}", hint or "fix its type", key)
        if isinstance(value, float) and not math.isfinite(value):
            raise self.error(f"expected a finite number, got {value!r}", hint or "give a finite value", key)
        return value

    def number(self, key: str, default: Any = ..., hint: str = "", positive: bool = False,
               nonnegative: bool = False) -> float:
        value = self.get(key, float, default, hint)
        if value is None or value is default and default is not ...:
            return value
        if positive and not value > 0 or nonnegative and not value >= 0:
            raise self.error(f"must be {'positive' if positive else '>= 0'}, got {value}", hint, key)
        return value

    def integer(self, key: str, default: Any = ..., hint: str = "", low: int = 0,
                high: int | None = None) -> int:
        value = self.get(key, int, default, hint)
        if value is default and default is not ...:
            return value
        if value < low or high is not None and value > high:
            bounds = f">= {low}" if high is None else f"between {low} and {high}"
            raise self.error(f"must be {bounds}, got {value}", hint, key)
        return value

    def names(self, key: str, allowed: tuple[str, ...] | None = None, default: Any = ...,
              hint: str = "", noun: str = "names") -> tuple[str, ...]:
        """A list of distinct strings (among ``allowed`` when given)."""
        value = self.get(key, list, default, hint)
        if value is default and default is not ...:
            return value
        if not all(isinstance(v, str) for v in value):
            raise self.error(f"expected a list of names, got {value!r}", hint or "write names in quotes", key)
        unknown = [v for v in value if allowed and v not in allowed]
        if unknown:
            raise self.error(f"has '{unknown[0]}'", f"allowed: {', '.join(allowed)}", key)
        if not value or len(set(value)) != len(value):
            what = f"distinct entries of {', '.join(allowed)}" if allowed else f"distinct {noun}"
            raise self.error(f"has {value}", f"list {what}", key)
        return tuple(value)

    def array(self, key: str, shape: tuple, default: Any = ..., hint: str = "") -> np.ndarray | Any:
        """A nested list of numbers (int or float, never strings or booleans) of ``shape``
        (None: any length), all finite."""
        value = self.get(key, list, default, hint)
        if value is default and default is not ...:
            return default
        want = " x ".join("any" if w is None else str(w) for w in shape)

        def flat(v: Any, depth: int) -> bool:
            if depth == 0:
                return _is_number(v)
            return isinstance(v, list) and all(flat(x, depth - 1) for x in v)

        if not flat(value, len(shape)):
            raise self.error(f"expected numbers of shape {want}, got {short(value)}",
                             hint or "give a list of numbers (not strings)", key)
        try:
            arr = np.array(value, dtype=float)
        except ValueError:  # ragged
            arr = np.zeros(0)
        ok = arr.ndim == len(shape) and all(w in (None, d) for w, d in zip(shape, arr.shape))
        if not ok or not np.all(np.isfinite(arr)):
            raise self.error(f"expected finite numbers of shape {want}, got {short(value)}",
                             hint or f"give {want} numbers", key)
        return arr

    def sub(self, key: str, required: bool = False) -> TableReader | None:
        if key not in self.table:
            if required:
                raise ProblemError(
                    f"{self.path}: [{self._name(key)}]: missing section; add a [{self._name(key)}] table"
                )
            return None
        value = self.table[key]
        if not isinstance(value, dict):
            raise self.error(f"expected a table, got {short(value)}", f"write it as [{self._name(key)}]", key)
        return TableReader(self.path, value, self._name(key), self.sections)

    def row(self, table: dict, section: str, label: str | None = None) -> TableReader:
        """A reader of ``table``, an entry of a list of tables of this file (keys of ``section``)."""
        return TableReader(self.path, table, section, self.sections, label)

    def _name(self, key: str) -> str:
        return f"{self.section}.{key}" if self.section else key


def short(value: Any, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def to_vec(a: np.ndarray | None) -> Vec | None:
    return None if a is None else tuple(float(v) for v in np.ravel(a))


def to_mat(a: np.ndarray | None) -> Mat | None:
    return None if a is None else tuple(tuple(float(v) for v in row) for row in np.asarray(a))


def check_size(path: str, where: str, count: int, limit: int, bytes_per_l2: int, what: str,
               fix: str, L: int | None = None) -> None:
    """Refuse ``count`` above ``limit`` with the memory it would need (for ``L`` parameters,
    or at least 10 when not yet known)."""
    if count <= limit:
        return
    need = count * bytes_per_l2 * (L or 10) ** 2
    raise ProblemError(f"{path}: {where}: {count} {what} would need {'about' if L else 'at least'} "
                       f"{need / 1e9:.3g} GB for the design NLP; {fix} (at most {limit})")


def check_load(r: TableReader, key: str, values, fix: str) -> None:
    """A wrench's components (N, N m) of the field ``key`` at most :data:`MAX_LOAD_N` in size."""
    largest = float(np.max(np.abs(np.asarray(values, dtype=float))))
    if largest > MAX_LOAD_N:
        raise r.error(f"has {largest:g}, above {MAX_LOAD_N:g} N (N m)", fix, key)
