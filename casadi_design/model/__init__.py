"""The problem as built: the file read and checked (``problem``), the robot (``robots``, ``ik``),
its kinematics in CasADi (``symbolic``, ``compiled``, ``mapped``), the measurement model and
base set (``models``, ``identifiability``), the cell's geometry (``obstacles``, ``segments``,
``capsules``, ``pairs``, ``collision``, ``cell``), the rules of one experiment (``rules``) and
the built ``Problem`` (``build``)."""
