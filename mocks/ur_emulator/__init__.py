"""An emulated Universal Robots e-Series controller that the real ``ur-rtde`` client talks to.

Tests run the unmodified ``rtde_control`` / ``rtde_receive`` client (PyPI ur-rtde 1.6.5) against
this process over loopback, so the UR driver is exercised on the wire, not through a Python
stand-in. The wire behaviour it reproduces is written down in ``/work/shared/docs/ur-rtde-wire.md``.

Run it as its own process (the client's constructors hold the GIL while they block)::

    python -m mocks.ur_emulator --host 127.0.0.2 [--instant] [--fault NAME[=VALUE] ...]

``--host auto`` serves on the first loopback address from 127.0.0.2 whose ports are free and
prints it as the first line on stdout; the ports stay bound until the process exits, so test
sessions running side by side never share an address.

It serves, on that one address, the dashboard (29999), the script port (30003, where the client
uploads its ``def rtde_control(): ... end`` program) and RTDE (30004). Instead of interpreting
URScript it runs a native twin of that program's main loop: the register handshake on
``output_int_register_<offset>`` (1 ready, 2 done) and the commands MOVEJ, MOVEJ_IK, MOVEL,
MOVEL_FK and STOP_SCRIPT; other commands are acknowledged and ignored.

Robot model: a UR5e (``mocks.ur_kinematics``), TCP = flange. moveJ interpolates joints and the
TCP pose follows by forward kinematics. moveL interpolates the pose along a straight line (slerp
for the rotation) and sets it directly; the joints follow by numerical IK seeded with the previous
joints, and are held where IK has no solution. Motions take the time of a trapezoidal velocity
profile from speed and acceleration, or no time with ``--instant``; after a timed motion the
reported TCP speed decays for ``--settle-time`` seconds, like a real arm ringing out.

Faults (``--fault`` at start, or at run time over the dashboard as
``emulator fault NAME[=VALUE]``; ``emulator clear`` removes them all and resets safety):

- ``protective_stop_during_move``: the next move stops half way; safety bit 2, program stopped.
- ``emergency_stop_during_move``: the same with an emergency stop (safety bit 7).
- ``program_never_starts``: uploaded programs never reach PLAYING.
- ``drop_during_move[=SECONDS]``: the next move closes every connection and resets new ones
  for SECONDS (default 1). ``emulator drop [SECONDS]`` does the same at once.
- ``slow_replies=SECONDS``: every RTDE and dashboard reply is delayed.
- ``local_control``: ``is in remote control`` answers ``false``.
- ``program_status_lag=SECONDS``: ``robot_status_bits`` shows a started program running only
  SECONDS later (``runtime_state`` at once), like a receive stream that lags the control one.

``--box X0,Y0,Z0,X1,Y1,Z1`` (with ``--tool-point X,Y,Z`` for points fixed to the flange, a
camera's) is the safety configuration: a move that would take the flange or a tool point out of
the box is refused with a protective stop before it starts (``safety``). ``--start-pose`` puts
the arm at a UR pose on start, as if jogged there.

The dashboard commands ``unlock protective stop`` and ``close safety popup`` clear a protective
stop as on a real controller. ``emulator state`` answers one JSON line (process id, joints,
pose, runtime state, safety bits, faults, and why each move the box refused was refused).
"""
