"""casadi_design: optimal design of robot calibration experiments with test-pose measures.

Read a problem file, build it, solve its designs: see ``casadi_design.cli`` and the README.
"""

from .build import Problem, build_problem, load_problem
from .errors import DesignError, ProblemError
from .problem import ProblemSpec, read_problem

__all__ = ["DesignError", "Problem", "ProblemError", "ProblemSpec", "build_problem", "load_problem", "read_problem"]
__version__ = "0.1.0"
