"""The problem file and its reader: one module per section with its plain data, keys and reader
(``robot``, ``calibration``, ``measurement``, ``poses``, ``experiments``, ``cell``, ``solver``); ``read`` puts them together."""
