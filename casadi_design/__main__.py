"""``python -m casadi_design ...``: the ``casadi-design`` command."""

import sys

from .cli import main

sys.exit(main())
