"""The error a call to a running service raises (``service.cli.client``), in a module of its
own so that ``service.cli.main`` catches it without importing the HTTP client."""


class ServiceCallError(Exception):
    """A call to the service failed: the service is down, refused the key, or answered an
    error; the message says which in one line."""
