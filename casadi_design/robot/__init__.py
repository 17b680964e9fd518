"""The robot and its kinematics: the Pinocchio model loaded and checked (``robots``), its
kinematics in CasADi (``symbolic``), compiled and mapped (``compiled``, ``mapped``), and IK (``ik``)."""
