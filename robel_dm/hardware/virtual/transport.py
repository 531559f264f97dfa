"""A virtual bus on a pseudo-terminal, as a client's serial port sees it.

`PtyBusServer` serves a `bus.Bus` on a pseudo-terminal from a daemon
thread; the unmodified `dynamixel_sdk` (or any Protocol 2.0 client) opens
`PtyBusServer.device_path` as if it were `/dev/ttyUSB0` (docs/dynamixel.md
section 4). Not modelled: wire timing and Return Delay Time (replies are
immediate).

A busy machine can hold the server's thread up past the SDK's reply
deadline (~34 ms), which a motor's reply never is: the server publishes
how far it has got on the pty itself (`protocol.encode_progress`), where a
`DynamixelClient` in any process reads it, waits while the bus is behind,
and calls a motor silent only once the bus has answered everything sent to
it.

`standalone_bus` runs `robel-virtual-bus` (a `PtyBusServer` in a process of
its own, in real time, as a robot's USB interface would be) for a program.
"""

import collections
from collections.abc import Iterator
import contextlib
import errno
import fcntl
import logging
import os
import select
import subprocess
import sys
import termios
import threading
import time
import tty

from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel import protocol
from robel_dm.hardware.virtual.bus import Bus

# termios speed constants -> bits per second, for the rates servos support.
_TERMIOS_SPEEDS = {
  getattr(termios, f'B{rate}'): rate
  for rate in table.BAUD_RATES.values()
  if hasattr(termios, f'B{rate}')
}
_READ_SIZE = 4096
_SEND_TIMEOUT_S = 0.1
_EIO_BACKOFF_S = 0.01


def _publish(master: int, answered: int) -> None:
  """Publishes the bytes answered, for clients to read at the pty's slave
  end (TIOCGWINSZ)."""
  fcntl.ioctl(master, termios.TIOCSWINSZ, protocol.encode_progress(answered))


class PtyBusServer:
  """Serves a `Bus` on a pseudo-terminal from a daemon thread.

  The client opens `device_path` like a serial port (pyserial, the SDK's
  `PortHandler`). The pty is put in raw mode at once, and the server keeps
  its own slave descriptor open for its whole life: otherwise the master
  reports EIO whenever the client has the port closed, e.g. while the SDK
  reopens it in `setBaudRate` (docs/dynamixel.md section 4.3).

  The thread blocks in `select()` on the master and a wake-up pipe, so an
  idle server uses no CPU. It reads the client's baud rate from the pty's
  settings (when `check_baud` is on and the rate is a standard one); servos
  set to another rate do not hear the packets, as on a real bus. Replies
  are written at once (no wire timing); if the client does not read them
  they are dropped after 0.1 s. Once it has answered, it publishes its
  'bytes_in' in the pty's window size (`protocol.encode_progress`).
  Exceptions raised while handling a packet are logged and collected in
  `errors`, and the server carries on (an error of the pty itself ends the
  thread, also recorded in `errors`).

  Attributes:
    bus: the bus served.
    errors: exceptions raised while handling packets.
    stats: Counter of 'bytes_in' (received and answered), 'bytes_out',
      'dropped' (reply bytes nobody read) and 'resyncs' (partial packets
      abandoned).
  """

  def __init__(
    self,
    bus: Bus,
    check_baud: bool = True,
    resync_timeout_s: float = 0.05,
  ):
    """Initializes the server (`start` opens the pty).

    Args:
      bus: the bus to serve.
      check_baud: whether servos ignore packets sent at another baud rate.
      resync_timeout_s: a partial packet with no new bytes for this long is
        abandoned (garbage that looked like a header).
    """
    self.bus = bus
    self.errors: list[BaseException] = []
    self.stats: collections.Counter[str] = collections.Counter()
    self._check_baud = check_baud
    self._resync_timeout_s = resync_timeout_s
    self._thread: threading.Thread | None = None
    self._fds: list[int] = []
    self._master = self._slave = self._wake_read = self._wake_write = -1
    self._path: str | None = None

  @property
  def device_path(self) -> str:
    """The pty's slave device, e.g. '/dev/pts/3' (after `start`)."""
    if self._path is None:
      raise RuntimeError('the server has not been started')
    return self._path

  @property
  def running(self) -> bool:
    return self._thread is not None and self._thread.is_alive()

  def start(self) -> 'PtyBusServer':
    """Opens the pty and starts serving; returns self.

    Raises:
      RuntimeError: if started before.
    """
    if self._thread is not None or self._path is not None:
      raise RuntimeError('a PtyBusServer can be started only once')
    master, slave = os.openpty()
    self._fds = [master, slave]
    try:
      tty.setraw(slave)
      _publish(master, 0)
      os.set_blocking(master, False)
      wake_read, wake_write = os.pipe()
      self._fds += [wake_read, wake_write]
      os.set_blocking(wake_write, False)
      self._path = os.ttyname(slave)
    except BaseException:
      self._close_fds()
      raise
    self._master, self._slave = master, slave
    self._wake_read, self._wake_write = wake_read, wake_write
    self._thread = threading.Thread(
      target=self._serve, name=f'virtual-bus {self._path}', daemon=True
    )
    self._thread.start()
    return self

  def stop(self, timeout_s: float = 5.0) -> None:
    """Stops serving, joins the thread and closes the pty (idempotent)."""
    thread = self._thread
    if thread is not None:
      with contextlib.suppress(OSError):
        os.write(self._wake_write, b'\0')
      thread.join(timeout_s)
      if thread.is_alive():
        logging.warning('virtual bus thread did not stop in %.1f s', timeout_s)
      self._thread = None
    self._close_fds()

  def __enter__(self) -> 'PtyBusServer':
    return self.start()

  def __exit__(self, *exc_info) -> None:
    self.stop()

  def _close_fds(self) -> None:
    for fd in self._fds:
      with contextlib.suppress(OSError):
        os.close(fd)
    self._fds = []

  def _client_baud(self) -> int | None:
    if not self._check_baud:
      return None
    try:
      return _TERMIOS_SPEEDS.get(termios.tcgetattr(self._slave)[5])
    except termios.error:
      return None

  def _serve(self) -> None:
    try:
      self._serve_forever()
    except Exception as error:
      logging.exception('virtual bus server on %s failed', self._path)
      self.errors.append(error)

  def _serve_forever(self) -> None:
    parser = protocol.PacketParser()
    watched = [self._master, self._wake_read]
    while True:
      timeout = self._resync_timeout_s if parser.pending else None
      ready, _, _ = select.select(watched, [], [], timeout)
      if self._wake_read in ready:
        return
      received = 0
      if not ready:
        self.stats['resyncs'] += 1
        packets = parser.resync()
      else:
        try:
          data = os.read(self._master, _READ_SIZE)
        except BlockingIOError:
          continue
        except OSError as error:
          if error.errno != errno.EIO:
            raise
          data = b''
        if not data:
          # No slave end open (cannot happen while ours is): back off
          # instead of spinning on a permanently readable master.
          if select.select([self._wake_read], [], [], _EIO_BACKOFF_S)[0]:
            return
          continue
        received = len(data)
        packets = parser.feed(data)
      if packets:
        self._answer(packets)
      # Counted once answered: a client that sent n bytes knows they are
      # processed when bytes_in reaches n.
      if received:
        self.stats['bytes_in'] += received
        _publish(self._master, self.stats['bytes_in'])

  def _answer(self, packets: list[protocol.Packet]) -> None:
    baud_rate = self._client_baud()
    replies = []
    for packet in packets:
      try:
        replies.append(self.bus.handle(packet, baud_rate))
      except Exception as error:  # A bug must not kill the server.
        logging.exception('virtual bus failed on %s', packet)
        self.errors.append(error)
    reply = b''.join(replies)
    if reply:
      self._send(reply)

  def _send(self, data: bytes) -> None:
    view = memoryview(data)
    deadline = time.monotonic() + _SEND_TIMEOUT_S
    while view:
      try:
        written = os.write(self._master, view)
      except BlockingIOError:
        written = 0
      except OSError as error:
        if error.errno != errno.EIO:
          raise
        break
      view = view[written:]
      self.stats['bytes_out'] += written
      remaining = deadline - time.monotonic()
      if view and remaining <= 0:
        break
      if view:
        select.select([], [self._master], [], remaining)
    self.stats['dropped'] += len(view)


# How long the bus may take to stop once asked, s.
_STANDALONE_STOP_TIMEOUT = 30.0


@contextlib.contextmanager
def standalone_bus(
  robot: str = 'dclaw', driver: str = 'sim', dynamics: str | None = None
) -> Iterator[str]:
  """Starts `robel-virtual-bus` and yields its device path.

  Args:
    robot: 'dclaw' or 'dkitty'.
    driver: 'sim' (a MuJoCo simulation of the robot, in real time) or
      'ideal' (every motor at its goal at once).
    dynamics: a calibration file of the simulated robot (driver 'sim').

  Raises:
    RuntimeError: if the bus prints no device path (it failed to start).
  """
  command = [
    sys.executable,
    '-m',
    'robel_dm.commands.virtual_bus',
    f'--robot={robot}',
    f'--driver={driver}',
  ]
  if dynamics:
    command.append(f'--dynamics={dynamics}')
  # A session of its own: a Ctrl-C meant for the program does not stop the
  # bus under it; the program stops it on the way out.
  process = subprocess.Popen(
    command,
    stdout=subprocess.PIPE,
    stderr=subprocess.DEVNULL,
    text=True,
    start_new_session=True,
  )
  try:
    device = process.stdout.readline().strip()
    if not device.startswith('/dev/'):
      raise RuntimeError(f'the virtual bus did not start: {device!r}')
    yield device
  finally:
    process.terminate()
    try:
      process.wait(_STANDALONE_STOP_TIMEOUT)
    except subprocess.TimeoutExpired:
      process.kill()
      process.wait()
