"""Running many designs: the loop over criteria and m (``campaign``), sweeps (``sweep``), workers
on processes or Dask (``parallel``) and the study a user asks for (``study``)."""
