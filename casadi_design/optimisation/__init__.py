"""The design NLPs and their solution: the reduced space (``reduced``, ``nlp``), multi-start IPOPT
(``solve``, ``ipopt``), approximate designs and certified bounds (``bound``)."""
