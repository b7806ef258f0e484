"""Exit statuses of ``cellcal`` commands (0 is success)."""

#: Bad input: a malformed file, option or address.
EXIT_USAGE = 2
#: The work failed: a device fault, an unreadable file, a failed check.
EXIT_FAILED = 1
#: ``cellcal calibrate``: the result was written, but its verdict is ``fail``.
EXIT_VERDICT_FAIL = 3
#: Stopped by Ctrl-C.
EXIT_INTERRUPTED = 130
