"""The cellcal version, in a module of its own: ``cellcal --version`` and the service's health
answer read it without loading the rest.

``VERSION`` is the one place the version is written: the package metadata takes it from here
(``pyproject.toml``, ``[tool.setuptools.dynamic]``), so reading it needs no
``importlib.metadata``, whose imports were a third of the CPU time of ``cellcal --version``.
"""

VERSION = "0.1.0"


def software_version() -> str:
    """The cellcal version."""
    return VERSION
