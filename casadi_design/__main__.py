"""``python -m casadi_design ...``: the ``casadi-design`` command."""

import sys

from .launch import main

sys.exit(main())
