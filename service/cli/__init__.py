"""The ``cellcal`` command line: ``main`` builds the parser from one module per command
(``calibrate``, ``demo``, ``devices``, ``export``, ``report``, ``serve``); the commands import
nothing from ``main``."""
