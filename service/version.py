"""The installed cellcal's version, in a module of its own: ``cellcal --version`` and the
service's health answer read it without loading the rest."""

from importlib.metadata import PackageNotFoundError, version


def software_version() -> str:
    """The installed package's version ("unknown" when run from an uninstalled tree)."""
    try:
        return version("cellcal")
    except PackageNotFoundError:
        return "unknown"
