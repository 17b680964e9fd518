"""The calibration and measurement model: what is identified and what each experiment measures,
B(q, F) and the errors it predicts (``models``), the base set (``identifiability``), prior information (``held``)."""
