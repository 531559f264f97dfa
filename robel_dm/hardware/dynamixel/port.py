"""One owner per serial port, and the port's OS errors as the library's.

Two programs (or two environments in one program) talking to the same bus
would interleave their packets, and both would read numbers that look right
and are not. A `DynamixelClient` therefore takes an exclusive lock on its
port (`flock`, which a second opener in this or another process cannot
take) right after opening it and before changing anything: a refused
opener neither configures the port (its line speed is the holder's too)
nor flushes it (the holder's pending reply), and is told who holds it. A
port that vanishes (USB adapter unplugged, bus process killed) makes
pyserial and termios raise their own errors; `port_errors` turns them into
`PortError`s naming the port. `port_handler_class` is the SDK's port as
the client opens it.
"""

from collections.abc import Callable, Iterator
import contextlib
import errno
import fcntl
import os
import termios
from typing import NoReturn

from robel_dm import constants
from robel_dm.hardware.dynamixel.errors import DynamixelError

# What the OS and pyserial raise when a port fails (pyserial's
# SerialException is an OSError).
OS_ERRORS = (OSError, termios.error)


class PortBusyError(DynamixelError):
  """The port is already open by another client (this process or not)."""


class PortError(DynamixelError):
  """The port itself failed (unplugged adapter, closed pty)."""


@contextlib.contextmanager
def port_errors(device_path: str, doing: str) -> Iterator[None]:
  """Raises OS-level port failures inside the block as `PortError`s."""
  try:
    yield
  except OS_ERRORS as error:
    raise PortError(
      f'{device_path} failed while {doing}: {error}; is the adapter still '
      'connected (and the bus process running)?'
    ) from None


def lock_exclusively(fd: int, device_path: str) -> None:
  """Takes the exclusive lock of an open port (again, if already held).

  Raises:
    PortBusyError: naming the port and, where the OS tells, the holder.
  """
  try:
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
  except BlockingIOError:
    raise _busy(device_path) from None


def _busy(device_path: str) -> PortBusyError:
  holders = _holders(device_path)
  held_by = f' (held by {", ".join(holders)})' if holders else ''
  return PortBusyError(
    f'{device_path} is already in use{held_by}: only one program, and one '
    'environment in it, may drive a bus; close the other first'
  )


def _holders(device_path: str) -> list[str]:
  """'pid N (command)' of the processes holding the port's lock, from
  /proc/locks (Linux); empty where the OS does not tell."""
  try:
    stat = os.stat(device_path)
    with open('/proc/locks') as locks:
      lines = locks.read().splitlines()
  except OSError:
    return []
  device = (
    f'{os.major(stat.st_dev):02x}:{os.minor(stat.st_dev):02x}:{stat.st_ino}'
  )
  own_pid = os.getpid()
  pids = []
  for line in lines:
    fields = line.split()
    # "1: FLOCK  ADVISORY  WRITE 1234 00:19:3 0 EOF"
    if len(fields) >= 6 and fields[1] == 'FLOCK' and fields[5] == device:
      pids.append(int(fields[4]))
  return [_describe(pid, own_pid) for pid in dict.fromkeys(pids)]


def _describe(pid: int, own_pid: int) -> str:
  if pid == own_pid:
    return f'this process, pid {pid}'
  try:
    with open(f'/proc/{pid}/cmdline', 'rb') as cmdline:
      command = cmdline.read().replace(b'\0', b' ').decode(errors='replace')
  except OSError:
    command = ''
  command = command.strip()
  return f'pid {pid}' + (f' ({command[:80]})' if command else '')


def _serial():
  """pyserial (from the optional `hardware` extra, as dynamixel_sdk)."""
  try:
    import serial  # noqa: PLC0415
  except ImportError as error:
    raise ImportError(
      f'the serial port needs pyserial ({error}): '
      + constants.INSTALL_EXTRA.format('hardware')
    ) from error
  return serial


class _RefusedPort:
  """The serial port of a `PortHandler` whose port another client holds.

  Nothing of the port was changed, and it is closed again. Every use raises
  the refusal; the client's first use is taking the port's lock
  (`lock_exclusively(port.ser.fileno(), ...)` after `openPort`).
  """

  def __init__(self, device_path: str):
    self._message = str(_busy(device_path))

  def refuse(self, *args) -> NoReturn:
    del args
    raise PortBusyError(self._message)

  fileno = read = write = reset_input_buffer = refuse

  @property
  def in_waiting(self) -> NoReturn:
    self.refuse()

  def close(self) -> None:
    pass  # Closed already.


def _open_locked(device_path: str, baud_rate: int):
  """The port as a pyserial `Serial`, opened and locked, then configured
  and flushed; a `_RefusedPort` if another client holds it."""
  serial = _serial()
  try:
    # exclusive: pyserial takes the lock right after opening the device,
    # before it sets the line (speed, DTR and RTS) or flushes it.
    return serial.Serial(
      port=device_path,
      baudrate=baud_rate,
      bytesize=serial.EIGHTBITS,
      timeout=0,
      exclusive=True,
    )
  except serial.SerialException as error:
    if error.errno != errno.EWOULDBLOCK:
      raise
  return _RefusedPort(device_path)


# How long a reply from a bus that is behind (see `DynamixelClient`'s
# `bus_progress`) is waited for, seconds: a hang guard for a bus whose
# thread stopped.
_BEHIND_BUS_LIMIT_S = 10.0


class _LockedSetup:
  """`PortHandler` setup: the port opened once and locked (see
  `_open_locked`), and 4.5 Mbps (missing from the SDK's list).

  A mixin for the SDK's PortHandler (its attributes and methods).
  """

  def getCFlagBaud(self, baudrate):  # noqa: N802 (SDK method name)
    if baudrate == 4_500_000:
      return baudrate
    return super().getCFlagBaud(baudrate)

  def setupPort(self, cflag_baud):  # noqa: N802 (SDK method name)
    # The SDK's closes and reopens a port to change its speed, dropping
    # the lock for a moment: the port is opened once, then reconfigured.
    del cflag_baud  # The SDK's own setup, too, uses self.baudrate.
    if isinstance(self.ser, _RefusedPort):
      return True  # The client's lock_exclusively raises the refusal.
    if self.is_open:
      self.ser.baudrate = self.baudrate
    else:
      self.ser = _open_locked(self.port_name, self.baudrate)
      if isinstance(self.ser, _RefusedPort):
        return True
      self.is_open = True
    self.ser.reset_input_buffer()
    self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
    return True


class _PatientTimeouts:
  """`PortHandler` timeouts: bytes counted both ways, and, for a bus that
  reports its progress, replies that come late because the machine is busy
  waited for (up to `_BEHIND_BUS_LIMIT_S`).

  A mixin for the SDK's PortHandler (its attributes and methods).
  """

  # Bytes the bus has answered of this port's output, and bytes it has
  # sent to it; None for a real bus, whose replies are due within the
  # SDK's deadline.
  progress: Callable[[], tuple[int, int]] | None = None
  written = read = 0
  _started = 0.0

  def writePort(self, packet):  # noqa: N802 (SDK method name)
    written = super().writePort(packet)
    self.written += written
    return written

  def readPort(self, length):  # noqa: N802 (SDK method name)
    data = super().readPort(length)
    self.read += len(data)
    return data

  def setPacketTimeout(self, packet_length):  # noqa: N802
    super().setPacketTimeout(packet_length)
    self._started = self.packet_start_time

  def setPacketTimeoutMillis(self, msec):  # noqa: N802
    super().setPacketTimeoutMillis(msec)
    self._started = self.packet_start_time

  def isPacketTimeout(self):  # noqa: N802
    if not super().isPacketTimeout():
      return False
    if self.progress is None:
      return True
    # Behind: a request not yet answered, or a reply not yet read (a pty
    # passes written bytes on asynchronously).
    answered, sent = self.progress()
    behind = answered < self.written or sent > self.read
    waited_s = (self.getCurrentTime() - self._started) / 1000.0
    if behind and waited_s < _BEHIND_BUS_LIMIT_S:
      self.packet_start_time = self.getCurrentTime()
      self.packet_timeout = 1.0  # Look again in a millisecond.
      return False
    return True


def port_handler_class() -> type:
  """The SDK's PortHandler, opening its port locked (see `_open_locked`),
  extended with 4.5 Mbps (missing from its list) and, for a bus that
  reports its progress, replies that come late because the machine is busy.
  Only the client calls it, once it has checked that the SDK is installed.

  Returns:
    The class: `_LockedSetup` and `_PatientTimeouts` over the SDK's.
  """
  import dynamixel_sdk as sdk  # noqa: PLC0415 (the optional hardware extra)

  class PortHandler(_LockedSetup, _PatientTimeouts, sdk.PortHandler):
    """The SDK's PortHandler, locked and patient (see `port_handler_class`)."""

  return PortHandler
