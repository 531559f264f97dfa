"""Every way a session ends leaves the motors released.

A connected `DynamixelClient` registers here (a strong reference: an
environment that is garbage-collected without `close()` still has its
motors released, at the latest at interpreter exit). At exit, and on
SIGTERM, SIGHUP (the terminal or SSH session closed) and SIGQUIT, every
registered client turns its motors' torque off, each in turn, whatever the
others raise. A release runs with those signals and SIGINT deferred: a
burst of Ctrl-C cannot stop it half-way; the signals take effect once it is
done. Only SIGKILL and power loss escape.

Exit signals: only the main thread can install a signal handler (and
Python runs it there), so this module installs its handler when the main
thread imports it, and again whenever a client connects from the main
thread, for each exit signal whose disposition is still the default. The
handler releases every registered robot at once, whichever thread drives
it: it takes the client's bus lock, so its packets never interleave with a
control step in another thread, and that client refuses every later
command with an error naming the signal. It then exits through
SystemExit(128 + signum); atexit handlers run once the other threads have
stopped. With no robot registered it does exactly what the default does
(the process dies of the signal). A program that connects from a worker
thread must import this module from the main thread first; if it did not,
the connection logs a warning saying so.
"""

import atexit
from collections.abc import Callable, Iterator
import contextlib
import logging
import signal
import threading

# Signals that end a session. SIGINT raises KeyboardInterrupt by Python's
# default; the others are made to exit through Python (so atexit runs).
DEFERRED_SIGNALS = (
  signal.SIGINT,
  signal.SIGTERM,
  signal.SIGHUP,
  signal.SIGQUIT,
)
EXIT_SIGNALS = (signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)

_LOCK = threading.RLock()
# Releasers of the connected clients: id(client) -> release callable.
_LIVE: dict[int, Callable[[], None]] = {}
# The exit signal whose handler released the robots (the program is ending).
_EXIT_SIGNAL: list[signal.Signals] = []
# Whether the handler is running (a repeated signal then changes nothing),
# and whether the warning about a worker thread's robot was logged.
_STATE = {'handling': False, 'warned': False}


def register(key: object, release: Callable[[], None]) -> None:
  """Keeps `release` to be called at exit until `unregister(key)`.

  From the main thread, also installs the exit-signal handler (where the
  signals still have their default action); from another thread, logs one
  warning if an exit signal would still kill the program unreleased.
  """
  with _LOCK:
    _LIVE[id(key)] = release
  if threading.current_thread() is threading.main_thread():
    install_exit_signals()
  else:
    _warn_if_unprotected()


def unregister(key: object) -> None:
  with _LOCK:
    _LIVE.pop(id(key), None)


def registered() -> int:
  """How many releasers are registered (for tests and diagnostics)."""
  with _LOCK:
    return len(_LIVE)


def exit_signal() -> signal.Signals | None:
  """The exit signal on which the robots were released, or None."""
  return _EXIT_SIGNAL[0] if _EXIT_SIGNAL else None


def release_all() -> None:
  """Calls every registered releaser; one failing never stops the others."""
  with _LOCK:
    releasers = list(_LIVE.values())
  for release in releasers:
    try:
      with deferred_signals():
        release()
    except BaseException as error:  # noqa: BLE001 (release every robot)
      logging.error('releasing motors at exit failed: %r', error)


@contextlib.contextmanager
def deferred_signals() -> Iterator[None]:
  """Holds back SIGINT, SIGTERM, SIGHUP and SIGQUIT while the block runs.

  Python runs signal handlers in the main thread only, so there the
  handlers are swapped for ones that note the signal; afterwards the noted
  signals are raised again, once each, under the original handlers. In
  other threads no handler can interrupt the block anyway.
  """
  if threading.current_thread() is not threading.main_thread():
    yield
    return
  noted = []

  def note(signum, frame):
    del frame
    if signum not in noted:
      noted.append(signum)

  previous = {}
  try:
    for signum in DEFERRED_SIGNALS:
      previous[signum] = signal.signal(signum, note)
    yield
  finally:
    for signum, handler in previous.items():
      signal.signal(signum, handler)
    for signum in noted:
      signal.raise_signal(signum)


def _on_exit_signal(signum, frame) -> None:
  """Releases every registered robot, then exits with 128 + signum; with
  none registered, dies of the signal as its default action would."""
  del frame
  if _STATE['handling']:
    return  # A repeat while the robots are being released: exiting anyway.
  with _LOCK:
    robots = bool(_LIVE)
  if not robots:
    signal.signal(signum, signal.SIG_DFL)
    signal.raise_signal(signum)
    return
  if not _EXIT_SIGNAL:
    _EXIT_SIGNAL.append(signal.Signals(signum))
  _STATE['handling'] = True
  try:
    release_all()
  finally:
    _STATE['handling'] = False
  raise SystemExit(128 + signum)


def install_exit_signals() -> None:
  """Makes SIGTERM, SIGHUP and SIGQUIT release the motors and exit through
  Python, unless the program handles them itself (main thread only)."""
  if threading.current_thread() is not threading.main_thread():
    return
  for signum in EXIT_SIGNALS:
    if signal.getsignal(signum) is signal.SIG_DFL:
      signal.signal(signum, _on_exit_signal)


def _warn_if_unprotected() -> None:
  """Warns once if an exit signal would kill the program unreleased."""
  unhandled = [
    signum.name
    for signum in EXIT_SIGNALS
    if signal.getsignal(signum) is signal.SIG_DFL
  ]
  with _LOCK:
    if not unhandled or _STATE['warned']:
      return
    _STATE['warned'] = True
  logging.warning(
    '%s will not release the torque of the motors connected from thread '
    '%r: they would kill the program at once (signal handlers can only be '
    'installed from the main thread). To avoid it, import '
    'robel_dm.hardware.shutdown in the main thread before starting the '
    'thread that drives the robot.',
    ', '.join(unhandled),
    threading.current_thread().name,
  )


install_exit_signals()
atexit.register(release_all)
