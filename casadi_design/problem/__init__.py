"""The problem built from its file: the robot, the calibration model, the cell and the test poses
put together (``build``: :class:`Problem`) and the rules of one experiment (``rules``)."""
