"""casadi_design: optimal design of robot calibration experiments with test-pose measures.

Read a problem file, build it, solve its designs: see ``casadi_design.cli`` and the README.
The names below are imported when first used, so that ``import casadi_design`` (and the
command's start, :mod:`casadi_design.launch`) costs nothing before Ctrl-C is handled.
"""

import importlib

#: The package's own names and the module that defines each.
_NAMES = {"DesignError": "errors", "ProblemError": "errors", "Problem": "problem.build",
          "build_problem": "problem.build", "load_problem": "problem.build",
          "ProblemSpec": "problem_file.read", "read_problem": "problem_file.read"}

__all__ = sorted(_NAMES)
__version__ = "0.1.0"


def __getattr__(name: str):
    if name not in _NAMES:
        raise AttributeError(f"module 'casadi_design' has no attribute '{name}'")
    return getattr(importlib.import_module(f".{_NAMES[name]}", __name__), name)
