"""How good a plan is: the criteria's registry (``criteria``), their reduced-space objectives
(``objectives``) and the scores of a plan, ``rho = sigma^2 trace(B0 M^-1 B0^T)`` and the
classical criteria (``measures``)."""
