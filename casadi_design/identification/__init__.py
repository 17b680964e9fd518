"""Identify a robot from measured tracker coordinates: read, register, fit, compensate, export.

Modules, in the order of the data: :mod:`.measurements` (measurement CSVs), :mod:`.registration`
(the tracker frame in closed form), :mod:`.lsq` (Levenberg-Marquardt on the one measurement
model, also the identification of every simulated calibration of ``validate``), :mod:`.fit`
(the fit's model with the tracker frame, the fit of some rows), :mod:`.compensate` (the test
poses' commands, shared with ``validate``), :mod:`.residuals` (the scale of the residuals: the
tracker's noise and the robot's unmodelled error, leverages, outlier scores), :mod:`.field_fit`
(the unmodelled error's field by restricted maximum likelihood), :mod:`.calibrate` (outliers,
statistics, validation rows, compensation), :mod:`.report` (``identification.json``, the summary, the compensated poses),
:mod:`.urdf` (``calibrated.urdf``), :mod:`.dh_table` (the calibrated DH table) and
:mod:`.calibrated_toml` (``calibrated.toml``, ``calibrated_dh.toml``); :mod:`.held` reads what a
second round starts from (measured experiments, an identification as a prior). The command
is ``casadi-design identify`` (:mod:`casadi_design.cli.identify`).
"""
