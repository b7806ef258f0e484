"""The cell's robot and camera as the service holds them (``devices``) and who moves the
robot (``motion``)."""
