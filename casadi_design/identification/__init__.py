"""Identify a robot from measurements: read, register, fit, compensate.

Modules, in the order of the data: :mod:`.measurements` (measurement CSVs), :mod:`.registration`
(the tracker frame in closed form), :mod:`.lsq` (Levenberg-Marquardt on the one measurement
model, also the identification of every simulated calibration of ``validate``), :mod:`.fit`
(the fit's model with the tracker frame, the fit of some rows), :mod:`.compensate` (the test
poses' commands, shared with ``validate``), :mod:`.residuals` (the scale of the residuals: the
tracker's noise and the robot's unmodelled error, leverages, outlier scores), :mod:`.field_fit`
(the unmodelled error's field by restricted maximum likelihood), :mod:`.calibrate` (outliers,
statistics, validation rows, compensation); without a tracker, :mod:`.recordings` (a ball
seated at an artefact's points) and :mod:`.artefact_fit` (their fit, model choice and figures);
:mod:`.held` reads what a second round starts from (measured experiments, an identification as
a prior). What is written of the calibrated robot: :mod:`casadi_design.calibrated`. The command
is ``casadi-design identify`` (:mod:`casadi_design.cli.identify`).
"""
