"""Virtual calibration of a design case: python scripts/validate_case.py problems/<case>.toml [options].

A thin wrapper over ``casadi-design validate`` (see ``--help``).
"""

import sys

from casadi_design.launch import main

if __name__ == "__main__":
    sys.exit(main(["validate", *sys.argv[1:]]))
