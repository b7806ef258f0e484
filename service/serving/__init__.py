"""Running the service: the HTTP server of ``cellcal serve`` (``server``) and its
bounded connections (``connections``), a service in a child process for the demo,
tests and benchmarks (``local``), and children that end with their parent
(``parent_death``)."""
