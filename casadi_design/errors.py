"""Error types: one for bad input, one for designs that cannot be produced.

Messages follow one format: where (file and field), what is wrong, what is allowed or what
to do, and what was given. They are meant to be printed as one line to a user.
"""


class ProblemError(ValueError):
    """A problem description (file, field or value) is invalid."""


class DesignError(RuntimeError):
    """A design could not be produced: infeasible constraints, no converged start, ..."""


class OutputError(ValueError):
    """An output folder or file cannot be written (or a results file read back) as asked."""
