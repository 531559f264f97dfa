"""A Dynamixel Protocol 2.0 client on the official `dynamixel_sdk`.

One `DynamixelClient` owns one serial port and a fixed set of motors. It
reads present current, velocity and position of every motor in one sync-read
transaction, writes goal positions in one sync write, switches torque, and
checks the hardware-error register (group reads drop the servos' alert bit,
so it has to be read on its own). Values are in motor units turned into SI:
motor angle in rad (ticks * 2 pi / 4096), velocity in rad/s, current in mA
(per model: W-series 2.69 mA, V-series 1.34 mA per unit).

Failures raise `DynamixelError`s that name the motors involved and how they
failed (silent, or corrupted replies; a silent bus is named as such).
Nothing stale is ever returned: a read either delivers fresh data for every
motor or raises. The state read also reads back each motor's Goal Position,
so a goal write lost on the way (a sync write has no reply) is noticed
within the control step, sent again and read back before the step returns,
and reported if it is lost again.

A client owns its port exclusively (see `port`), and until it disconnects it
is registered with `shutdown`, which releases its motors however the
session ends. Every transaction holds the client's bus lock: a release from
another thread (an exit signal) never interleaves its packets with a
control step's, and once the client is closed every transaction raises.
"""

from collections.abc import Callable
import fcntl
import logging
import select
import struct
import termios
import threading

import numpy as np

from robel_dm import constants
from robel_dm.hardware import shutdown
from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel import port as port_lib

# Re-exported: callers catch `dynamixel.DynamixelError` and its subclasses.
from robel_dm.hardware.dynamixel import protocol, register_access
from robel_dm.hardware.dynamixel.errors import (  # noqa: F401
  DynamixelError,
  MissingMotorError,
  MotorFaultError,
  RobotReleasedError,
  describe_hardware_errors,
)
from robel_dm.hardware.dynamixel.port import PortBusyError, PortError  # noqa: F401

try:
  import dynamixel_sdk as sdk
except ImportError:  # pragma: no cover - exercised without the extra
  sdk = None

# The state block (control_table.STATE_BLOCK_*): goal position (4), realtime
# tick, moving, moving status and PWM (6, skipped), current (2), velocity (4),
# position (4).
_STATE_FORMAT = struct.Struct('<i6xhii')
# A goal write found missing is sent again (and read back) this often; still
# missing then, it is an error.
_GOAL_RESENDS = 1


def _published_progress(fd: int) -> int | None:
  """The bytes a virtual bus on this pseudo-terminal has answered, all
  told, as it publishes them; None for any other port."""
  try:
    winsize = fcntl.ioctl(fd, termios.TIOCGWINSZ, bytes(8))
  except OSError:
    return None
  return protocol.decode_progress(winsize)


def _require_sdk():
  if sdk is None:
    raise ImportError(
      'dynamixel_sdk is not installed: '
      + constants.INSTALL_EXTRA.format('hardware')
    )


class DynamixelClient(register_access.RegisterAccess):
  """Talks to a fixed set of motors on one port.

  Use as a context manager, or call `connect()` and `disconnect()`;
  `disconnect()` always tries to turn every motor's torque off first.
  """

  def __init__(
    self,
    device_path: str,
    motor_ids,
    baud_rate: int = table.DEFAULT_BAUD_RATE,
    retries: int = 2,
    bus_progress: Callable[[], tuple[int, int]] | None = None,
  ):
    """Initializes the client (no I/O until `connect`).

    Args:
      device_path: serial device, e.g. '/dev/ttyUSB0'.
      motor_ids: the motors' Dynamixel IDs.
      baud_rate: bits per second (1 Mbps default; up to 4.5 Mbps).
      retries: how often a failed transaction is repeated before giving up.
      bus_progress: for a simulated bus only: how many bytes sent to it it
        has answered and how many it has sent, all told (only the first
        count is used). A reply is then waited for while the bus has a
        request unanswered or a reply unread (a busy machine delays a
        simulated bus's replies, never a motor's), and only a reply the bus
        did not send times out, after the SDK's usual deadline. None: the
        same if the port is a virtual bus's pseudo-terminal (it publishes
        its count there, for a client in any process); for a real bus
        every reply is due within that deadline.

    Raises:
      ValueError: for repeated or out-of-range IDs, or a bad baud rate.
      ImportError: if dynamixel_sdk is not installed.
    """
    _require_sdk()
    ids = tuple(int(i) for i in motor_ids)
    if (
      not ids
      or len(set(ids)) != len(ids)
      or not all(0 <= i <= 252 for i in ids)
    ):
      raise ValueError(f'motor IDs must be distinct, in 0..252: {ids}')
    if baud_rate not in table.BAUD_RATES.values():
      raise ValueError(f'{baud_rate} is not a Dynamixel baud rate')
    self._device_path = device_path
    self._ids = ids
    self._baud_rate = baud_rate
    self._retries = max(0, int(retries))
    self._bus_progress = bus_progress
    self._port = None
    self._packets = None
    self._models: dict[int, int] = {}
    self._current_units = np.zeros(len(ids))
    self._state = np.zeros((3, len(ids)))  # current, velocity, position.
    # Goal ticks last sent to each motor, and whether a read has yet to
    # confirm them.
    self._sent_goals = np.zeros(len(ids), dtype=np.int64)
    self._goal_pending = np.zeros(len(ids), dtype=bool)
    self._column = {motor_id: i for i, motor_id in enumerate(ids)}
    # Held by every transaction, and by a release or disconnect throughout.
    self._bus_lock = threading.RLock()
    self._transaction = None  # Ident of the thread inside a transaction.
    self._bus_silent = False  # Known to answer nothing: skip confirmations.
    self._state_reader = None
    self._goal_writer = None
    self._register_readers = {}  # Address -> GroupSyncRead of all motors.
    self._probing = False  # Connected without checking the motors.

  # --- Connection ----------------------------------------------------------

  @property
  def motor_ids(self) -> tuple[int, ...]:
    return self._ids

  @property
  def is_connected(self) -> bool:
    return self._port is not None

  @property
  def models(self) -> dict[int, int]:
    """Model number of each motor (after `connect`)."""
    return dict(self._models)

  def connect(self, check_motors: bool = True) -> None:
    """Opens the port and checks that every motor answers.

    Args:
      check_motors: whether to ping every motor and require a supported
        model (the default). False only opens the port, for tools that probe
        the bus (`broadcast_ping`, `ping`, `read_bytes`, `read_register`,
        `write_register`, `set_torque`): `read_state` and
        `write_goal_positions` are unavailable then, and `disconnect` leaves
        every motor's torque as it is.

    Raises:
      DynamixelError: if the port cannot be opened or set up.
      MissingMotorError: naming the motors that do not answer.
    """
    if self._port is not None:
      return
    if shutdown.exit_signal() is not None:
      raise self._not_connected()
    port = self._open_port()
    self._port = port
    self._packets = register_access.packet_handler()
    self._probing = not check_motors
    self._bus_silent = False
    shutdown.register(self, self._release_at_exit)
    if self._probing:
      return
    try:
      self._check_motors(port)
    except BaseException:
      self._close_port()
      raise

  def _open_port(self):
    """Opens, sets up and locks the port (closed again if that fails)."""
    port = port_lib.port_handler_class()(self._device_path)
    try:
      opened = port.openPort()
    except Exception as error:  # pyserial raises SerialException/OSError.
      raise DynamixelError(
        f'cannot open {self._device_path}: {error}'
      ) from error
    if not opened or not port.setBaudRate(self._baud_rate):
      port.closePort()
      raise DynamixelError(
        f'cannot open {self._device_path} at {self._baud_rate} baud'
      )
    try:
      port_lib.lock_exclusively(port.ser.fileno(), self._device_path)
      self._follow_bus_progress(port)
    except BaseException:
      port.closePort()
      raise
    return port

  def _check_motors(self, port) -> None:
    """Pings every motor, requires supported models, and sets up the
    group read of their state and the group write of their goals."""
    failed = {}  # Motor ID -> (result, bad reply) of its last ping.
    for motor_id in self._ids:
      model, result = self._ping_result(motor_id)
      if model is None:
        failed[motor_id] = result, self._packets.bad_reply
      else:
        self._models[motor_id] = model
    if failed:
      raise MissingMotorError(self._connect_failure(failed), failed)
    unknown = {i: m for i, m in self._models.items() if m not in table.MODELS}
    if unknown:
      raise DynamixelError(
        f'unsupported motor models (ID: model number) {unknown}; '
        f'supported: {sorted(table.MODELS)}',
        unknown,
      )
    self._current_units[:] = [
      table.MODELS[self._models[i]][1] for i in self._ids
    ]
    self._state_reader = sdk.GroupSyncRead(
      port,
      self._packets,
      table.STATE_BLOCK_ADDRESS,
      table.STATE_BLOCK_SIZE,
    )
    for motor_id in self._ids:
      self._state_reader.addParam(motor_id)
    self._goal_writer = sdk.GroupSyncWrite(
      port,
      self._packets,
      table.GOAL_POSITION.address,
      table.GOAL_POSITION.size,
    )

  def _follow_bus_progress(self, port) -> None:
    """Makes the port wait for a virtual bus that is behind: its count of
    bytes answered comes from `bus_progress`, or from the bus's pty."""
    if self._bus_progress is not None:
      progress = self._bus_progress

      def answered() -> int | None:
        return progress()[0]

    else:
      fd = port.ser.fileno()

      def answered() -> int | None:
        return _published_progress(fd)

    baseline = answered()
    if baseline is None:
      return  # A real bus.

    def since_connect() -> tuple[int, int]:
      count = answered()
      if count is None:  # The bus is gone: nothing more comes.
        return port.written, port.read
      # A reply is unread while the port has bytes to read (a pty hands
      # what was written to the next select), not while the bus has sent
      # more than was read: the SDK clears the port before every packet.
      unread = select.select([port.ser], [], [], 0)[0]
      return count - baseline, port.read + len(unread)

    port.progress = since_connect

  def disconnect(self) -> None:
    """Turns every motor's torque off (best effort) and closes the port.

    The torque-off goes out first as one broadcast (no reply needed, so a
    partly silent bus cannot delay it), then each motor's is confirmed. No
    signal interrupts it, and a failing port does not stop it. After
    `connect(check_motors=False)` the torque is left as it is.
    """
    with shutdown.deferred_signals(), self._bus_lock:
      if self._port is None:
        return
      try:
        if not self._probing:
          self._release_all()
      finally:
        self._close_port()

  def release(self) -> None:
    """Turns every motor's torque off now, leaving the port open.

    Like `disconnect`, never interrupted by a signal and never stopped by a
    failing port (failures are logged).
    """
    with shutdown.deferred_signals(), self._bus_lock:
      if self._port is not None and not self._probing:
        self._release_all()

  def _release_at_exit(self) -> None:
    """`disconnect`, at exit or on an exit signal, from whichever thread.

    The bus lock waits for another thread's transaction to end; the client
    then refuses every command. A transaction of this thread that the
    signal interrupted is left to unwind (its error releases the motors,
    and atexit does at the latest).
    """
    if self._transaction != threading.get_ident():
      self.disconnect()

  def _release_all(self) -> None:
    """Torque off for every motor: broadcast, then confirmed by each, those
    that miss it asked again for a while (`confirm_torque_off`)."""
    try:
      with port_lib.port_errors(self._device_path, 'releasing the motors'):
        self._call(
          self._packets.write1ByteTxOnly,
          sdk.BROADCAST_ID,
          table.TORQUE_ENABLE.address,
          0,
        )
        if self._bus_silent:
          return
        held = self.confirm_torque_off(self._ids)
    except port_lib.PortError as error:
      logging.error('could not release the motors: %s', error)
      return
    if held:
      logging.error(
        'motors %s on %s did not confirm their torque off within %.1f s '
        '(a broadcast asked every motor): they may still hold it',
        held,
        self._device_path,
        register_access.RELEASE_CONFIRM_S,
      )

  def _close_port(self) -> None:
    port, self._port = self._port, None
    self._register_readers = {}
    self._state_reader = self._goal_writer = None
    shutdown.unregister(self)
    if port is not None:
      port.is_using = False
      try:
        port.closePort()  # Also drops the port's lock.
      except port_lib.OS_ERRORS as error:
        logging.error('closing %s failed: %s', self._device_path, error)

  def __enter__(self) -> 'DynamixelClient':
    self.connect()
    return self

  def __exit__(self, *exc_info) -> None:
    self.disconnect()

  # --- Transactions ----------------------------------------------------------

  def _check_connected(self) -> None:
    if self._port is None:
      raise self._not_connected()

  def _not_connected(self) -> DynamixelError:
    signum = shutdown.exit_signal()
    if signum is None:
      return DynamixelError(f'not connected to {self._device_path}')
    return DynamixelError(
      f'the motors on {self._device_path} were released on {signum.name}: '
      'the program is exiting, and nothing more is sent'
    )

  def _check_motors_checked(self) -> None:
    self._check_connected()
    if self._state_reader is None:
      raise DynamixelError(
        f'connected to {self._device_path} without checking the motors: '
        'use connect() for reads and writes of all motors'
      )

  def _call(self, function, *args):
    """Runs one SDK transaction under the bus lock; clears the SDK's port
    lock around it.

    An exception inside the SDK leaves `port.is_using` set, after which
    every call would answer COMM_PORT_BUSY (docs/dynamixel.md section 3.5).

    Raises:
      DynamixelError: if the client is not connected (any more).
    """
    with self._bus_lock:
      port = self._port
      if port is None:
        raise self._not_connected()
      self._transaction = threading.get_ident()
      port.is_using = False
      try:
        with port_lib.port_errors(self._device_path, 'talking to the motors'):
          return function(port, *args)
      finally:
        self._transaction = None
        port.is_using = False

  def ping(self, motor_id: int, attempts: int | None = None) -> int:
    """Pings a motor and returns its model number.

    Args:
      motor_id: the motor.
      attempts: how often to try; 1 + the client's retries by default.

    Raises:
      MissingMotorError: if it gives no valid reply: none, or (the message
        says so) a corrupted one or one of the wrong length.
    """
    self._check_connected()
    model, result = self._ping_result(motor_id, attempts)
    if model is None:
      how = self._ping_failure(result, self._packets.bad_reply)
      raise MissingMotorError(
        f'motor {motor_id} {how} on {self._device_path}', [motor_id]
      )
    return model

  def _ping_result(
    self, motor_id: int, attempts: int | None = None
  ) -> tuple[int | None, int]:
    """(model number or None, the SDK's result of the last attempt)."""
    result = None
    for _ in range(self._retries + 1 if attempts is None else attempts):
      model, result, _ = self._call(self._packets.ping, motor_id)
      if result == sdk.COMM_SUCCESS:
        return model, result
    return None, result

  def read_state(self) -> np.ndarray:
    """Reads current (mA), velocity (rad/s) and position (rad) of all motors.

    The same transaction reads back each motor's Goal Position: a goal sent
    since the last read that did not arrive is sent again (and logged); lost
    twice in a row, it raises.

    Returns:
      A (3, n) array, rows current, velocity, position, columns in
      `motor_ids` order. The array is reused by the next call.

    Raises:
      MissingMotorError: naming the motors that stopped answering, or the
        whole bus if none answers.
      DynamixelError: naming the motors whose replies are corrupted or of
        the wrong length, or whose goal writes keep getting lost; or the
        whole bus if it stalled (no reply to the read, yet every motor
        answers a ping right after).
    """
    self._check_motors_checked()
    reader = self._state_reader
    # (first motor without a valid reply, SDK result, the handler's
    # `bad_reply` for a reply of the wrong length).
    failures = []
    for _ in range(self._retries + 1):
      result = self._call(lambda port: reader.txRxPacket())
      short = self._first_unread(reader)
      if result == sdk.COMM_SUCCESS and short is None:
        break
      bad_reply = None
      if result == register_access.COMM_WRONG_LENGTH:
        # A well-formed reply of another length: a late reply to an earlier
        # packet (a ping that timed out) was taken for this motor's. Drop
        # whatever else is waiting and read again.
        bad_reply = self._packets.bad_reply
        self._call(lambda port: port.clearPort())
      elif result == sdk.COMM_SUCCESS:  # A reply missing, yet no error.
        result = sdk.COMM_RX_CORRUPT
        self._call(lambda port: port.clearPort())
      failures.append((short, result, bad_reply))
    else:
      raise self._read_failure(failures)
    # Every motor answered: a bus once found silent is back, and releases
    # confirm each motor again.
    self._bus_silent = False
    state = self._state
    goals = np.empty(len(self._ids), dtype=np.int64)
    for column, motor_id in enumerate(self._ids):
      goal, *state[:, column] = _STATE_FORMAT.unpack(
        bytes(reader.data_dict[motor_id])
      )
      goals[column] = goal
    state[0] *= self._current_units
    state[1] *= table.RADIANS_PER_SECOND_PER_UNIT
    state[2] *= table.RADIANS_PER_TICK
    if self._goal_pending.any():
      self._confirm_goals(goals)
    return state

  def _first_unread(self, reader) -> int | None:
    """The motor at which a failed sync read stopped (the SDK reads the
    replies in order and stops at the first bad one)."""
    for motor_id in self._ids:
      if len(reader.data_dict.get(motor_id) or ()) != table.STATE_BLOCK_SIZE:
        return motor_id
    return None

  def _confirm_goals(self, goals: np.ndarray) -> None:
    """Checks that the motors hold the goals last sent; re-sends lost ones
    and reads them back (nothing returns while a goal is unconfirmed).

    Raises:
      DynamixelError: naming motors whose goal is still missing after
        `_GOAL_RESENDS` re-sends.
    """
    lost = np.flatnonzero(self._goal_pending & (goals != self._sent_goals))
    self._goal_pending[:] = False
    for _ in range(_GOAL_RESENDS):
      if not lost.size:
        return
      ids = [self._ids[i] for i in lost]
      logging.warning('goal write lost on motors %s: sent again', ids)
      self._send_goal_ticks(self._sent_goals[lost], ids)
      held = self.read_register(table.GOAL_POSITION, ids)
      self._goal_pending[:] = False  # Read back: confirmed, or raised below.
      lost = np.array(
        [i for i in lost if held[self._ids[i]] != self._sent_goals[i]], int
      )
    if lost.size:
      ids = [self._ids[i] for i in lost]
      raise DynamixelError(
        f'motors {ids} did not take their goal positions '
        f'{_GOAL_RESENDS + 1} times in a row on {self._device_path} '
        '(lost packets, or goals beyond their position limits)',
        ids,
      )

  def write_goal_positions(self, positions, motor_ids=None) -> None:
    """Sends goal positions (motor angles, rad) in one sync write.

    Args:
      positions: one goal per motor of `motor_ids`.
      motor_ids: the motors to command; all motors if None.

    Raises:
      ValueError: for a wrong number of positions, unknown motors or
        non-finite values; nothing is sent then.
      DynamixelError: if the packet cannot be sent.
    """
    self._check_motors_checked()
    ids = self._ids if motor_ids is None else tuple(motor_ids)
    unknown = set(ids) - set(self._ids)
    if unknown:
      raise ValueError(f'motors {sorted(unknown)} are not on this client')
    positions = np.asarray(positions, dtype=float)
    if positions.shape != (len(ids),):
      raise ValueError(f'{positions.size} goal positions for {len(ids)} motors')
    if not np.all(np.isfinite(positions)):
      raise ValueError(f'non-finite goal positions: {positions.tolist()}')
    ticks = np.rint(positions / table.RADIANS_PER_TICK).astype(np.int64)
    self._send_goal_ticks(ticks, ids)

  def _send_goal_ticks(self, ticks: np.ndarray, ids) -> None:
    def send(port) -> int:
      del port  # The writer's.
      writer = self._goal_writer  # Under the bus lock: set while connected.
      writer.clearParam()
      for motor_id, tick in zip(ids, ticks.tolist(), strict=True):
        raw = table.to_unsigned(tick, table.GOAL_POSITION.size)
        writer.addParam(motor_id, list(raw.to_bytes(4, 'little')))
      return writer.txPacket()

    result = self._call(send)
    if result != sdk.COMM_SUCCESS:
      raise DynamixelError(
        f'sending goal positions failed: {self._packets.getTxRxResult(result)}',
        ids,
      )
    columns = [self._column[motor_id] for motor_id in ids]
    self._sent_goals[columns] = ticks
    self._goal_pending[columns] = True
