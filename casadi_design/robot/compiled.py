"""Compiled CasADi functions: a function's C code, built once per machine and kept on disk.

The large functions of a 6-axis robot in its cell (the kinematics and its derivatives of
:mod:`casadi_design.optimisation.reduced`, the capsule rows and their curvature, the rule rows of one
configuration) run 3 to 16 times faster as C than in CasADi's virtual machine, and the
objective and non-capsule rules of the bound's searches over one experiment (a UR10 search
about 1.6 times faster); the searches reach their capsule rows through the capsules' points and the
rows' compiled switches of the design NLP (:func:`casadi_design.optimisation.approximate._search_rows`), not a
library per row of z. :func:`compiled` writes a function's C code
(``casadi.CodeGenerator``), compiles it with the system's C compiler into a shared library in
the cache directory, named by a hash of the function's serialization
(``Function.serialize``, the exact algorithm), the CasADi version that writes its code and
the compiler command, and loads it (``casadi.external``); a later run, or another process,
finds the library there and pays only the serialization (the code is written only for a
library to build: for the UR10's 300 capsule-row functions 0.25 s instead of 1.07 s).
Libraries are written under a lock to a temporary name and renamed, so a killed run leaves no
half-written library and two processes never build one twice.

The C code performs the same floating-point operations in the same order as the virtual machine:
no ``-ffast-math`` and no contraction into fused multiply-adds (``-ffp-contract=off``), so the
results, and every plan, are the same to the bit (a test checks it). Without a C compiler, with
``CASADI_DESIGN_COMPILE=0``, or for a function too small to gain (``MIN_INSTRUCTIONS``), the
function is returned as it is.

Environment: ``CASADI_DESIGN_COMPILE`` (0: never compile), ``CASADI_DESIGN_CACHE`` (the
directory, :func:`casadi_design.runtime.cache.cache_dir`), ``CC`` (the compiler; default ``cc``).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import casadi as ca

from ..runtime.cache import cache_dir, digest
from ..runtime.threads import cpu_count

#: Functions (or groups of a switch's cases) of fewer virtual-machine instructions stay as they
#: are: their call costs more than their arithmetic, and compiling them would cost more than
#: it saves (the paper's planar arm compiles nothing).
MIN_INSTRUCTIONS = 1000
#: The same for a function evaluated over many inputs at once (mapped): there the arithmetic
#: outweighs the call from a few hundred instructions on (the UR10's screen rows, 404
#: instructions, over 300 000 configurations: 0.64 s in the virtual machine, 0.10 s compiled).
MAPPED_MIN_INSTRUCTIONS = 100
#: The compiler's flags: optimised, but exactly IEEE (no reassociation, no fused multiply-add).
#: ``-Og`` rather than ``-O1``: gcc's register allocation over one straight-line function of
#: tens of thousands of temporaries is most of a compile, and ``-Og`` does it in about a
#: quarter of the time (the UR10 search Hessian ``d2d``, 935 kB of C) for code as fast (a warm
#: UR10 start within 2 %, the approximate designs within the machine's noise) and the same
#: results, so a solve from an empty cache (a UR10 or ABB design of one start) takes a tenth to
#: a quarter less time.
FLAGS = ("-Og", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math")

_groups: dict[tuple[int, ...], tuple[list, list]] = {}  # (min_instructions, ids): fns, compiled
_said: list[str] = []


def enabled() -> bool:
    """Whether functions are compiled: ``CASADI_DESIGN_COMPILE`` is not 0 and a compiler exists."""
    return os.environ.get("CASADI_DESIGN_COMPILE", "1") != "0" and _compiler() is not None


def _compiler() -> str | None:
    return shutil.which(os.environ.get("CC", "cc"))


def instructions(fn: ca.Function) -> int:
    """Virtual-machine instructions of an SX function (0 for any other kind)."""
    return fn.n_instructions() if fn.class_name() == "SXFunction" else 0


def _source(fn: ca.Function) -> str:
    """The C code of ``fn`` (its entry point named ``fn.name()``)."""
    with tempfile.TemporaryDirectory() as tmp:
        gen = ca.CodeGenerator("f.c", {"with_header": False})
        gen.add(fn)
        gen.generate(tmp + os.sep)
        return (Path(tmp) / "f.c").read_text()


def _name(fn: ca.Function, compiler: str) -> str:
    """The library's name: what decides its code (the function's serialization and the CasADi
    version that writes the code) and how it is compiled."""
    return digest(fn.serialize().encode(), ca.__version__.encode(), compiler.encode(), " ".join(FLAGS).encode())


def _build(source: str, target: Path, compiler: str) -> None:
    """Compile ``source`` into the library ``target`` (written under a temporary name first)."""
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        c, so = Path(tmp) / "f.c", Path(tmp) / target.name
        c.write_text(source)
        subprocess.run([compiler, *FLAGS, str(c), "-o", str(so), "-lm"], check=True,
                       capture_output=True, text=True)
        os.replace(so, target)


def compiled(fn: ca.Function) -> ca.Function:
    """``fn`` as compiled code (the same inputs, outputs and results; :func:`compiled_group`)."""
    return compiled_group([fn])[0]


def compiled_group(fns: Sequence[ca.Function], min_instructions: int = MIN_INSTRUCTIONS) -> list[ca.Function]:
    """The functions ``fns`` as compiled code (the same inputs, outputs and results), or as they
    are when compiling is off or their instructions together number fewer than
    ``min_instructions``. The missing libraries are built in parallel, one compiler per core;
    a function asked for again is not generated again."""
    fns = list(fns)
    key = (min_instructions, *(id(f) for f in fns))
    if key not in _groups:
        _groups[key] = (fns, _compile(fns, min_instructions))  # holds fns: their ids stay theirs
    return list(_groups[key][1])


def _compile(fns: list[ca.Function], min_instructions: int) -> list[ca.Function]:
    if not fns or not enabled() or sum(instructions(f) for f in fns) < min_instructions:
        return fns
    compiler, directory = _compiler(), cache_dir()
    keys = [_name(f, compiler) for f in fns]
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with open(directory / "lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # one process builds; the others wait, then load
            todo = {k: f for k, f in zip(keys, fns) if not (directory / f"{k}.so").exists()}
            sources = {k: _source(f) for k, f in todo.items()}
            with ThreadPoolExecutor(max_workers=cpu_count()) as pool:
                list(pool.map(lambda k: _build(sources[k], directory / f"{k}.so", compiler), todo))
    except (OSError, subprocess.CalledProcessError) as exc:
        _say(f"casadi-design: could not compile CasADi functions in {directory} ({_reason(exc)}); "
             "they run in CasADi's virtual machine (the same results, slower)")
        return fns
    return [ca.external(f.name(), str(directory / f"{k}.so")) for k, f in zip(keys, fns)]


def compiled_switch(name: str, cases: Sequence[ca.Function]) -> ca.Function:
    """``casadi.Function.conditional(name, cases, cases[0])`` over the compiled cases
    (:func:`compiled_group`: their instructions counted together)."""
    cases = compiled_group(cases)
    return ca.Function.conditional(name, cases, cases[0])


def _reason(exc: Exception) -> str:
    if isinstance(exc, subprocess.CalledProcessError):
        lines = (exc.stderr or "").strip().splitlines()
        return lines[-1] if lines else f"exit {exc.returncode}"
    return str(exc)


def _say(message: str) -> None:
    if message not in _said:
        _said.append(message)
        print(message, file=sys.stderr)
