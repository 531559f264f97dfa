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

Ctrl-C: Python's default stays (KeyboardInterrupt in the main thread),
but once Ctrl-C has been pressed, the end of the main thread releases every
robot at once. Python would otherwise wait, the robot driven on, for a
non-daemon worker thread that drives it, until a second Ctrl-C. A daemon
thread waits for both events, in either order: a program that catches the
interrupt keeps its robot while its main thread runs. The robot's later
commands raise an error naming SIGINT. A program that installs its own
SIGINT handler keeps it, and this does not apply.

A robot belongs to the process that connected it. A forked child
(`os.fork`, multiprocessing's fork start method) inherits the registry and
the exit handler, and neither releases the parent's robots there; its
signals get Python's default handling back (a terminated child dies of
SIGTERM) until it connects a robot of its own. `HardwareRobot` refuses to
drive the parent's robots from the child.
"""

import atexit
from collections.abc import Callable, Iterator
import contextlib
import logging
import os
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
# Releasers of the connected clients: id(client) -> (the pid of the process
# that connected it, its release callable). A forked child inherits them.
_LIVE: dict[int, tuple[int, Callable[[], None]]] = {}
# The signal on which the robots were released (the program is ending).
_EXIT_SIGNAL: list[signal.Signals] = []
# Whether the handler is running (a repeated signal then changes nothing),
# whether the warning about a worker thread's robot was logged, and the
# process whose thread releases the robots after Ctrl-C (see
# `_release_after_interrupt`).
_STATE = {'handling': False, 'warned': False, 'watcher_pid': 0}
# Set by the first Ctrl-C (SIGINT under this module's handler).
_INTERRUPTED = threading.Event()
# The forking thread's signal mask while it forks (see `_before_fork`).
_FORK = threading.local()


def register(key: object, release: Callable[[], None]) -> None:
  """Keeps `release` to be called at exit until `unregister(key)`.

  Only this process calls it: a forked child leaves it to its parent.
  From the main thread, also installs the exit-signal handler (where the
  signals still have their default action); from another thread, logs one
  warning if an exit signal would still kill the program unreleased.
  """
  with _LOCK:
    _LIVE[id(key)] = (os.getpid(), release)
  _watch_for_interrupts()
  if threading.current_thread() is threading.main_thread():
    install_exit_signals()
  else:
    _warn_if_unprotected()


def unregister(key: object) -> None:
  with _LOCK:
    _LIVE.pop(id(key), None)


def _own_releasers() -> list[Callable[[], None]]:
  """The releasers of the robots this process connected."""
  pid = os.getpid()
  with _LOCK:
    return [release for owner, release in _LIVE.values() if owner == pid]


def exit_signal() -> signal.Signals | None:
  """The signal on which the robots were released, or None."""
  return _EXIT_SIGNAL[0] if _EXIT_SIGNAL else None


def _note_exit_signal(signum: int) -> None:
  with _LOCK:
    if not _EXIT_SIGNAL:
      _EXIT_SIGNAL.append(signal.Signals(signum))


def release_all() -> None:
  """Calls every releaser this process registered; one failing never
  stops the others."""
  for release in _own_releasers():
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
  if not _own_releasers():  # None, or only a parent's (a forked child).
    signal.signal(signum, signal.SIG_DFL)
    signal.raise_signal(signum)
    return
  _note_exit_signal(signum)
  _STATE['handling'] = True
  try:
    release_all()
  finally:
    _STATE['handling'] = False
  raise SystemExit(128 + signum)


def _on_interrupt(signum, frame) -> None:
  """Notes the Ctrl-C for `_release_after_interrupt`, then raises
  KeyboardInterrupt as Python's default handler does."""
  _INTERRUPTED.set()
  if not threading.main_thread().is_alive():
    # Python only waits for worker threads now: the program is ending.
    _note_exit_signal(signum)
  signal.default_int_handler(signum, frame)


def _watch_for_interrupts() -> None:
  """Starts this process's `_release_after_interrupt` thread, once."""
  with _LOCK:
    if _STATE['watcher_pid'] == os.getpid():
      return
    _STATE['watcher_pid'] = os.getpid()
  threading.Thread(
    target=_release_after_interrupt,
    name='robel_dm release after Ctrl-C',
    daemon=True,
  ).start()


def _release_after_interrupt() -> None:
  """Once the main thread has ended and Ctrl-C was pressed, releases every
  robot, then lets Python wait for the threads that drove them."""
  threading.main_thread().join()
  _INTERRUPTED.wait()
  _note_exit_signal(signal.SIGINT)
  release_all()


def _release_at_exit() -> None:
  """The exit handler: the robots' commands name a Ctrl-C that ended the
  program, if one did."""
  if _INTERRUPTED.is_set():
    _note_exit_signal(signal.SIGINT)
  release_all()


def _our_signals() -> dict[int, object]:
  """Signal -> Python's default handling, for those handled here."""
  defaults = dict.fromkeys(EXIT_SIGNALS, signal.SIG_DFL)
  defaults[signal.SIGINT] = signal.default_int_handler
  ours = (_on_exit_signal, _on_interrupt)
  return {s: d for s, d in defaults.items() if signal.getsignal(s) in ours}


def _before_fork() -> None:
  """Holds this module's signals back in the forking thread.

  Python drops a signal that reaches a child before its fork is complete
  (a Pool worker that is still starting then outlives terminate()). Held
  back, it stays pending in both processes until `_after_fork_*`.
  """
  _FORK.mask = signal.pthread_sigmask(signal.SIG_BLOCK, _our_signals())


def _after_fork_in_parent() -> None:
  mask = getattr(_FORK, 'mask', None)
  if mask is not None:
    _FORK.mask = None
    signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def _after_fork_in_child() -> None:
  """A forked child starts unlocked and uninterrupted, with no thread of
  its own waiting for Ctrl-C, and with Python's signal handling (a SIGTERM
  held back during the fork then kills it) until it connects a robot of
  its own; its parent's robots stay registered, and are skipped, as the
  parent's."""
  global _LOCK, _INTERRUPTED  # noqa: PLW0603 (fresh copies in the child)
  _LOCK = threading.RLock()  # Another thread may hold the parent's.
  _INTERRUPTED = threading.Event()
  _STATE['handling'] = False
  with contextlib.suppress(ValueError):  # Not the main interpreter.
    for signum, default in _our_signals().items():
      signal.signal(signum, default)
  _after_fork_in_parent()  # Restores the signal mask.


def install_exit_signals() -> None:
  """Makes SIGTERM, SIGHUP and SIGQUIT release the motors and exit through
  Python, and notes Ctrl-C (see the module's docstring), unless the program
  handles them itself (main thread only)."""
  if threading.current_thread() is not threading.main_thread():
    return
  for signum in EXIT_SIGNALS:
    if signal.getsignal(signum) is signal.SIG_DFL:
      signal.signal(signum, _on_exit_signal)
  if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
    signal.signal(signal.SIGINT, _on_interrupt)


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
atexit.register(_release_at_exit)
os.register_at_fork(
  before=_before_fork,
  after_in_parent=_after_fork_in_parent,
  after_in_child=_after_fork_in_child,
)
