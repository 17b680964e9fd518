"""casadi_design: optimal robot calibration experiments for the accuracy needed at test poses.

Flow: problem file -> robot model -> symbolic kinematics -> calibration model (B) ->
measures -> NLP -> multi-start solve -> results -> plots / CLI.
"""

from .errors import DesignError, ProblemError
from .problem import Problem, load_problem

__all__ = ["DesignError", "Problem", "ProblemError", "load_problem"]
__version__ = "0.1.0"
