"""Command line: design, sweep, score and plot calibration plans.

    casadi-design solve    problems/<case>.toml --out DIR      optimal plans, Table 4, Fig. 1
    casadi-design sweep    problems/<case>.toml --m 1:10 --out DIR   accuracy vs m per criterion
    casadi-design evaluate problems/<case>.toml --plan plan.csv      score your own plan
    casadi-design plot     DIR/sweep.json                       redraw the figures
    casadi-design validate problems/<case>.toml --results DIR   simulate the calibration
    casadi-design bound    problems/<case>.toml --m 1:10        what no plan can beat
    casadi-design identify problems/<case>.toml --measurements meas.csv --out DIR   calibrate
    casadi-design program  problems/<case>.toml --plan plan.csv --format urscript --out DIR   robot program

Errors in the input or a design that cannot be produced print one line ``error: ...`` and exit
with code 2; files are written only once the work they describe is done (a sweep also keeps
each finished design in ``sweep.partial.json``; Ctrl-C exits with code 130 and ``--resume``
continues).

One module per command (``solve``, ``sweep``, ``evaluate``, ``plot``, ``validate``, ``bound``,
``identify``, ``program``),
each reading its arguments, calling the package and writing; what they share is in
:mod:`.common`.
"""

from __future__ import annotations

import argparse
import sys
import threading

from ..records import files
from ..runtime import interrupt
from ..runtime.interrupt import EXIT_INTERRUPTED
from ..errors import DesignError, OutputError, ProblemError
from ..execution.parallel import MissingExtraError
from ..execution.study import Interrupted
from . import bound, evaluate, identify, plot, program, solve, sweep, validate

EXIT_ERROR = 2
#: The commands, in the order of ``--help``.
COMMANDS = (solve, sweep, evaluate, plot, bound, validate, identify, program)


class ArgumentError(ValueError):
    """A command-line option is wrong (raised instead of argparse's usage block)."""


class OneLineParser(argparse.ArgumentParser):
    """argparse with errors as one line ``error: <command>: <what>; <what to do>``."""

    def error(self, message: str) -> None:
        raise ArgumentError(f"{self.prog}: {message}; see {self.prog} --help")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="casadi-design", formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split("\n\n")[0] + "\n\n" + __doc__.split("\n\n")[1],
        epilog="Units: lengths and errors in mm for people (tables, CSV plans), SI (m, rad, N) "
               "in the JSON files. `casadi-design COMMAND --help` explains each option.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if threading.current_thread() is threading.main_thread():
        interrupt.install()
    files.start_log()
    try:
        args = build_parser().parse_args(argv)
        return args.run(args)
    except (ArgumentError, ProblemError, DesignError, OutputError, MissingExtraError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:  # a file operation the commands do not name themselves
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"error: {where}{exc.strerror or exc}; check the path, the free space and the "
              "permissions, then run the command again", file=sys.stderr)
        return EXIT_ERROR
    except Interrupted as exc:
        print(exc, file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception:
        if not interrupt.pressed():  # a bug: its traceback is the report
            raise
        # Ctrl-C inside a CasADi call outside a solve (building a solver runs Python callbacks)
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
