"""Child processes of the tests get the signal dispositions a program run
from a terminal has.

A command started in the background by a non-interactive shell (`cmd &`)
ignores SIGINT and SIGQUIT, one started by `nohup` ignores SIGHUP, and
their children inherit that; the tests that send those signals to a child
would then test a program that cannot receive them. Pass
`preexec_fn=child_signals.default` to their Popen.
"""

import signal


def default() -> None:
  """Runs in the child before it starts: SIGINT, SIGQUIT and SIGHUP by
  default."""
  for signum in (signal.SIGINT, signal.SIGQUIT, signal.SIGHUP):
    signal.signal(signum, signal.SIG_DFL)
