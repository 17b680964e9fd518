"""Virtual calibration: check the predicted accuracy by simulating the whole calibration.

For a plan ``{(q_i, F_i)}, i = 1..m`` the design step predicts the RMS error after
compensation at each test pose, ``sqrt(rho_j)`` with ``rho_j = sigma^2 trace(B0_j M^-1 B0_j^T)``
(m^2, ../shared/paper/MATH.md sections 1-3). That prediction rests on the linearised model
``y = B X``. Here every step of a real calibration is simulated ``N`` times on the problem's
own nonlinear measurement model (:class:`casadi_design.calibration.models.CalibrationModel`: markers,
load-point moment, joint deflection fixed point and noise model included):

1. a true robot (:mod:`.simulate`): random errors of the identified geometric parameters
   (normal, std :class:`ErrorSpreads`) and random true compliances (log-normal around a
   nominal value);
2. the plan's measurements (:mod:`.simulate`): ``model.measurement`` of the true robot, whose
   values are whitened, plus noise ``sigma`` per value;
3. identification (:mod:`.identify`): least squares on ``model.measurement`` (scipy's trust
   region, exact Jacobian), the code that identifies a robot from measured data
   (:mod:`casadi_design.identification`);
4. compensation (:mod:`.compensate`): at each test pose ``(q0_j, F0_j)`` the command ``q_c`` for
   which the identified robot puts the frame on the nominal target (``model.accuracy`` = 0,
   machining wrench included; Newton-chord iterations); the residual error is
   ``model.accuracy`` of the true robot at ``q_c``;
5. the empirical RMS of the residual error over the trials, next to ``sqrt(rho_j)`` (from
   ``model.B_stack`` and :func:`casadi_design.measures.measures.score_plan`), with a chi-square
   confidence interval (:mod:`.statistics`).

The simulation and the compensation of every trial of a plan run at once (CasADi functions
mapped over the stacked trials, numpy for the batched linear algebra); the fits one after
another. Plans with the same m share their true robots and noise draws
(common random numbers, generator ``default_rng([seed, m])``), which sharpens the comparison
between criteria.

Modules: :mod:`.simulate`, :mod:`.identify`, :mod:`.compensate`, :mod:`.statistics` (the
steps), :mod:`.validation` (a plan's simulated calibrations), :mod:`.plans` (which plans),
:mod:`.report` (text and ``validation.json``). The command is ``casadi-design validate``
(:mod:`casadi_design.cli.validate`).
"""

from .plans import plans_from_designs, plans_from_results
from .report import format_report, validation_record, write_validation
from .simulate import ErrorSpreads, Plan, evaluate
from .statistics import CONFIDENCE, rankings
from .validation import PlanValidation, Validation, linearisation_study, simulate_plan, validate

__all__ = [
    "CONFIDENCE", "ErrorSpreads", "Plan", "PlanValidation", "Validation", "evaluate",
    "format_report", "linearisation_study", "plans_from_designs", "plans_from_results", "rankings",
    "simulate_plan", "validate", "validation_record", "write_validation",
]
