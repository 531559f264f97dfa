"""Every way a session ends leaves the motors released.

A connected `DynamixelClient` registers here (a strong reference: an
environment that is garbage-collected without `close()` still has its
motors released, at the latest at interpreter exit). At exit, and on
SIGTERM, SIGHUP (the terminal or SSH session closed) and SIGQUIT, which are
turned into a normal exit, every registered client turns its motors' torque
off, each in turn, whatever the others raise. A release runs with those
signals and SIGINT deferred: a burst of Ctrl-C cannot stop it half-way; the
signals take effect once it is done. Only SIGKILL and power loss escape.
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


def register(key: object, release: Callable[[], None]) -> None:
  """Keeps `release` to be called at exit until `unregister(key)`."""
  with _LOCK:
    _LIVE[id(key)] = release


def unregister(key: object) -> None:
  with _LOCK:
    _LIVE.pop(id(key), None)


def registered() -> int:
  """How many releasers are registered (for tests and diagnostics)."""
  with _LOCK:
    return len(_LIVE)


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


def _exit_on_signal(signum, frame) -> None:
  del frame
  raise SystemExit(128 + signum)


def install_exit_signals() -> None:
  """Makes SIGTERM, SIGHUP and SIGQUIT exit through Python (so the motors
  are released) unless the program handles them itself (main thread)."""
  if threading.current_thread() is not threading.main_thread():
    return
  for signum in EXIT_SIGNALS:
    if signal.getsignal(signum) is signal.SIG_DFL:
      signal.signal(signum, _exit_on_signal)


atexit.register(release_all)
