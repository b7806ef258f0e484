"""The service's storage: the database (``db``), its rows (``records``), every query
and write (``queries``), stored stations and targets (``stations``) and which calibration
is active (``active``), keyset pages (``pages``), this service among the others on the database
(``instances``) and events relayed between services (``event_relay``)."""
