"""What several test modules share: the simulated cell's station sets (``stations``), result
documents (``results``), the service with a key and a temporary database (``service``), the
CLI as a child process (``cli``), a headless browser (``browser``), the UR controller emulator
(``ur_emulator``), a throwaway PostgreSQL server (``postgres``) and small checks (``helpers``).
Fixtures are in ``tests/conftest.py``."""
