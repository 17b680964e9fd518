"""Designs as files: ``results.json`` (``results``), atomic writes and the output folder
(``files``), plan CSVs and the report (``export``)."""
