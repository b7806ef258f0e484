"""Capture runs: the manager (``manager``), the capture thread (``capture``) and where the
robot goes (``planning``)."""

from service.runs.manager import RunManager

__all__ = ["RunManager"]
