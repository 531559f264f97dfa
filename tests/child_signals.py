"""Child processes of the tests get the signal dispositions a program run
from a terminal has.

A command started in the background by a non-interactive shell (`cmd &`)
ignores SIGINT and SIGQUIT, and its children inherit that; the tests that
send those signals to a child would then test a program that cannot
receive them. Pass `preexec_fn=child_signals.default` to their Popen.
"""

import signal


def default() -> None:
  """Runs in the child before it starts: SIGINT and SIGQUIT by default."""
  for signum in (signal.SIGINT, signal.SIGQUIT):
    signal.signal(signum, signal.SIG_DFL)
