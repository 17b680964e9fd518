"""From a plan to a robot program: the order of the experiments, moves that cannot collide,
and the code a controller runs.

* :mod:`.order`: the time of a synchronous joint-space move (trapezoidal speed profile of
  each joint, the slowest joint sets the time), the load changes between experiments, and
  the order of the experiments that minimises the load changes first and then the time from
  and back to home (Held-Karp up to ``order.EXACT_UP_TO`` experiments, 2-opt / or-opt beyond).
* :mod:`.moves`: each move checked along its whole path with the cell's capsule rows
  (:attr:`casadi_design.problem.rules.PlanRules.pose`) and the real meshes
  (:func:`casadi_design.cell.cell.clearances`);
* :mod:`.detours`: a blocked move's via points, found by a search over collision-free
  configurations;
* :mod:`.sequence`: the program as a sequence of checked moves.
* :mod:`.formats`: the controller mapping of ``[robot.controller]`` and the writers of
  URScript, ABB RAPID, KUKA KRL, the ROS robot_calibration poses YAML and a JSON joint
  trajectory.
"""
