"""The cell and its collision geometry: the cell as described (``spec``), obstacles, the robot's
capsules and their pairs, distances (``segments``, ``collision``) and the built cell (``cell``)."""
