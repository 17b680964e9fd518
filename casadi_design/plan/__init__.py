"""A plan of experiments: its rules (joint limits, loads, workspace, the cell; ``rules``), random
feasible plans (``sampling``) and a designed plan as data (``design``)."""
