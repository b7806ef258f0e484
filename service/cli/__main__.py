"""``python -m service.cli``: the ``cellcal`` command."""

import sys

from service.cli.main import main

sys.exit(main())
