"""For people: text tables in mm (``tables``) and figures (``plotting``)."""
