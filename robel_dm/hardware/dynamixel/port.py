"""One owner per serial port, and the port's OS errors as the library's.

Two programs (or two environments in one program) talking to the same bus
would interleave their packets, and both would read numbers that look right
and are not. A `DynamixelClient` therefore takes an exclusive lock on its
port when it opens it (`flock`, which a second opener in this or another
process cannot take) and names the holder when the lock is taken. A port
that vanishes (USB adapter unplugged, bus process killed) makes pyserial
and termios raise their own errors; `port_errors` turns them into
`PortError`s naming the port.
"""

from collections.abc import Iterator
import contextlib
import fcntl
import os
import termios

import serial

from robel_dm.hardware.dynamixel.errors import DynamixelError

# What the OS and pyserial raise when a port fails.
OS_ERRORS = (OSError, termios.error, serial.SerialException)


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
  """Takes the exclusive lock of an open port.

  Raises:
    PortBusyError: naming the port and, where the OS tells, the holder.
  """
  try:
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
  except BlockingIOError:
    holders = _holders(device_path, own_fd=fd)
    held_by = f' (held by {", ".join(holders)})' if holders else ''
    raise PortBusyError(
      f'{device_path} is already in use{held_by}: only one program, and one '
      'environment in it, may drive a bus; close the other first'
    ) from None


def _holders(device_path: str, own_fd: int) -> list[str]:
  """'pid N (command)' of the processes holding the port's lock, from
  /proc/locks (Linux); empty where the OS does not tell."""
  del own_fd
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
