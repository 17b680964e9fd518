"""Solve a design case: python scripts/solve_case.py problems/<case>.toml [--out DIR]."""

import sys

from casadi_design.launch import main

if __name__ == "__main__":
    sys.exit(main(["solve", *sys.argv[1:]]))
