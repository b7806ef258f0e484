"""The service's jobs: calibrations and their worker processes (``calibrations``,
``solve``, ``workers``), validations (``validations``): the dot-hit run (``validation_run``) and
the re-check (``checks``)."""
