"""``python -m service.cli``: the ``cellcal`` command."""

from service.cli.main import entry

entry()
