"""A plan of experiments: the checks of a whole plan (every experiment's rules, distinct
experiments, the real meshes; ``rules``), random feasible plans (``sampling``) and a designed
plan as data (``design``)."""
