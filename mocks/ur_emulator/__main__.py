"""``python -m mocks.ur_emulator``: serve until killed (see the package docstring)."""

from mocks.ur_emulator.server import main

main()
