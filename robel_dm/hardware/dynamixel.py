"""A Dynamixel Protocol 2.0 client on the official `dynamixel_sdk`.

One `DynamixelClient` owns one serial port and a fixed set of motors. It
reads present current, velocity and position of every motor in one sync-read
transaction, writes goal positions in one sync write, switches torque, and
checks the hardware-error register (group reads drop the servos' alert bit,
so it has to be read on its own). Values are in motor units turned into SI:
motor angle in rad (ticks * 2 pi / 4096), velocity in rad/s, current in mA
(per model: W-series 2.69 mA, V-series 1.34 mA per unit).

Failures raise `DynamixelError`s that name the motors involved. Nothing
stale is ever returned: a read either delivers fresh data for every motor
or raises.
"""

import atexit
import logging
import struct
import threading
import time
import weakref

import numpy as np

from robel_dm.hardware import control_table as table

# Re-exported: callers catch `dynamixel.DynamixelError` and its subclasses.
from robel_dm.hardware.dynamixel_errors import (
  DynamixelError,
  MissingMotorError,
  MotorFaultError,
  describe_hardware_errors,
)

try:
  import dynamixel_sdk as sdk
except ImportError:  # pragma: no cover - exercised without the extra
  sdk = None

_STATE_FORMAT = struct.Struct('<hii')  # current (2), velocity (4), position.
_TORQUE_RETRY_INTERVAL_S = 0.05


def _require_sdk():
  if sdk is None:
    raise ImportError(
      'dynamixel_sdk is not installed: pip install "robel_dm[hardware]"'
    )


def _port_handler_class():
  """The SDK's PortHandler, extended with 4.5 Mbps (missing from its list)."""

  class PortHandler(sdk.PortHandler):
    def getCFlagBaud(self, baudrate):  # noqa: N802 (SDK method name)
      if baudrate == 4_500_000:
        return baudrate
      return super().getCFlagBaud(baudrate)

  return PortHandler


# Open clients, closed at interpreter exit so no motor keeps its torque.
_OPEN_CLIENTS: 'weakref.WeakSet[DynamixelClient]' = weakref.WeakSet()
_OPEN_CLIENTS_LOCK = threading.Lock()


@atexit.register
def _close_all_clients():
  with _OPEN_CLIENTS_LOCK:
    clients = list(_OPEN_CLIENTS)
  for client in clients:
    client.disconnect()


class DynamixelClient:
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
  ):
    """Initializes the client (no I/O until `connect`).

    Args:
      device_path: serial device, e.g. '/dev/ttyUSB0'.
      motor_ids: the motors' Dynamixel IDs.
      baud_rate: bits per second (1 Mbps default; up to 4.5 Mbps).
      retries: how often a failed transaction is repeated before giving up.

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
    self._port = None
    self._packets = None
    self._models: dict[int, int] = {}
    self._current_units = np.zeros(len(ids))
    self._state = np.zeros((3, len(ids)))  # current, velocity, position.
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
    port = _port_handler_class()(self._device_path)
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
    self._port = port
    self._packets = sdk.PacketHandler(table.PROTOCOL_VERSION)
    self._probing = not check_motors
    with _OPEN_CLIENTS_LOCK:
      _OPEN_CLIENTS.add(self)
    if self._probing:
      return
    try:
      missing = []
      for motor_id in self._ids:
        model = self._ping(motor_id)
        if model is None:
          missing.append(motor_id)
        else:
          self._models[motor_id] = model
      if missing:
        raise MissingMotorError(
          f'motors {missing} do not answer on {self._device_path}; check '
          'wiring, power, IDs and baud rate',
          missing,
        )
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
    except BaseException:
      self._close_port()
      raise

  def disconnect(self) -> None:
    """Turns every motor's torque off (best effort) and closes the port.

    After `connect(check_motors=False)` the torque is left as it is.
    """
    if self._port is None:
      return
    if self._probing:
      self._close_port()
      return
    try:
      for motor_id in self._ids:
        for _ in range(self._retries + 1):
          result, _ = self._call(
            self._packets.write1ByteTxRx,
            motor_id,
            table.TORQUE_ENABLE.address,
            0,
          )
          if result == sdk.COMM_SUCCESS:
            break
        else:
          logging.error('could not turn off torque of motor %d', motor_id)
    finally:
      self._close_port()

  def _close_port(self) -> None:
    port, self._port = self._port, None
    self._register_readers = {}
    self._state_reader = self._goal_writer = None
    with _OPEN_CLIENTS_LOCK:
      _OPEN_CLIENTS.discard(self)
    if port is not None:
      port.is_using = False
      port.closePort()

  def __enter__(self) -> 'DynamixelClient':
    self.connect()
    return self

  def __exit__(self, *exc_info) -> None:
    self.disconnect()

  # --- Transactions ----------------------------------------------------------

  def _check_connected(self) -> None:
    if self._port is None:
      raise DynamixelError(f'not connected to {self._device_path}')

  def _check_motors_checked(self) -> None:
    self._check_connected()
    if self._state_reader is None:
      raise DynamixelError(
        f'connected to {self._device_path} without checking the motors: '
        'use connect() for reads and writes of all motors'
      )

  def _call(self, function, *args):
    """Runs one SDK transaction; clears the SDK's port lock around it.

    An exception inside the SDK leaves `port.is_using` set, after which
    every call would answer COMM_PORT_BUSY (docs/dynamixel.md section 3.5).
    """
    self._port.is_using = False
    try:
      return function(self._port, *args)
    finally:
      self._port.is_using = False

  def ping(self, motor_id: int) -> int:
    """Pings a motor and returns its model number.

    Raises:
      MissingMotorError: if it does not answer.
    """
    self._check_connected()
    model = self._ping(motor_id)
    if model is None:
      raise MissingMotorError(f'motor {motor_id} does not answer', [motor_id])
    return model

  def _ping(self, motor_id: int) -> int | None:
    for _ in range(self._retries + 1):
      model, result, _ = self._call(self._packets.ping, motor_id)
      if result == sdk.COMM_SUCCESS:
        return model
    return None

  def broadcast_ping(self) -> dict[int, tuple[int, int]]:
    """Pings every ID at once (Broadcast Ping; takes ~0.8 s whatever answers).

    Returns:
      Motor ID -> (model number, firmware version) of the motors that
      answered. A garbled reply loses the motors after it: ping the motors
      that must be there one by one to be sure.

    Raises:
      DynamixelError: if the ping cannot be sent.
    """
    self._check_connected()
    found, result = self._call(self._packets.broadcastPing)
    if result not in (
      sdk.COMM_SUCCESS,
      sdk.COMM_RX_TIMEOUT,
      sdk.COMM_RX_CORRUPT,
    ):
      raise DynamixelError(
        f'broadcast ping failed: {self._packets.getTxRxResult(result)}'
      )
    return {
      motor_id: (model, firmware)
      for motor_id, (model, firmware) in sorted(found.items())
    }

  def _silent_motors(self, motor_ids) -> list[int]:
    return [i for i in motor_ids if self._ping(i) is None]

  def read_state(self) -> np.ndarray:
    """Reads current (mA), velocity (rad/s) and position (rad) of all motors.

    Returns:
      A (3, n) array, rows current, velocity, position, columns in
      `motor_ids` order. The array is reused by the next call.

    Raises:
      MissingMotorError: if motors stop answering (named).
      DynamixelError: if the transaction keeps failing.
    """
    self._check_motors_checked()
    reader = self._state_reader
    result = None
    for _ in range(self._retries + 1):
      self._port.is_using = False
      try:
        result = reader.txRxPacket()
      finally:
        self._port.is_using = False
      if result == sdk.COMM_SUCCESS and all(
        reader.isAvailable(i, table.STATE_BLOCK_ADDRESS, table.STATE_BLOCK_SIZE)
        for i in self._ids
      ):
        break
    else:
      silent = self._silent_motors(self._ids)
      if silent:
        raise MissingMotorError(
          f'motors {silent} stopped answering on {self._device_path}', silent
        )
      raise DynamixelError(
        f'reading motors {list(self._ids)} failed: '
        f'{self._packets.getTxRxResult(result)}',
        self._ids,
      )
    state = self._state
    for column, motor_id in enumerate(self._ids):
      state[:, column] = _STATE_FORMAT.unpack(bytes(reader.data_dict[motor_id]))
    state[0] *= self._current_units
    state[1] *= table.RADIANS_PER_SECOND_PER_UNIT
    state[2] *= table.RADIANS_PER_TICK
    return state

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
    writer = self._goal_writer
    writer.clearParam()
    for motor_id, tick in zip(ids, ticks.tolist(), strict=True):
      raw = table.to_unsigned(tick, table.GOAL_POSITION.size)
      writer.addParam(motor_id, list(raw.to_bytes(4, 'little')))
    result = self._call(lambda port: writer.txPacket())
    if result != sdk.COMM_SUCCESS:
      raise DynamixelError(
        f'sending goal positions failed: {self._packets.getTxRxResult(result)}',
        ids,
      )

  def set_torque(self, motor_ids, enabled: bool) -> None:
    """Turns the torque of `motor_ids` on or off, and checks it took.

    Raises:
      DynamixelError: naming motors that refuse (e.g. after a shutdown).
      MotorFaultError: if a motor reports a hardware error.
    """
    self._check_connected()
    failed = []
    alerted = []
    for motor_id in motor_ids:
      for attempt in range(self._retries + 1):
        result, error = self._call(
          self._packets.write1ByteTxRx,
          motor_id,
          table.TORQUE_ENABLE.address,
          int(enabled),
        )
        if result == sdk.COMM_SUCCESS and not error & ~table.ALERT_BIT:
          if error & table.ALERT_BIT:
            alerted.append(motor_id)
          break
        if attempt < self._retries:
          time.sleep(_TORQUE_RETRY_INTERVAL_S)
      else:
        failed.append(motor_id)
    if alerted and enabled:
      self.raise_on_hardware_errors(alerted)
    if failed:
      raise DynamixelError(
        f'motors {failed} did not accept torque {"on" if enabled else "off"}',
        failed,
      )
    if enabled:
      values = self.read_register(table.TORQUE_ENABLE, motor_ids)
      refused = [i for i, value in values.items() if value != 1]
      if refused:
        self.raise_on_hardware_errors(refused)
        raise DynamixelError(f'motors {refused} kept their torque off', refused)

  def read_register(self, item: table.Item, motor_ids=None) -> dict[int, int]:
    """Reads one control-table item of each motor (individual reads).

    Returns:
      Motor ID -> value (signed items decoded).

    Raises:
      MissingMotorError: naming motors that do not answer.
    """
    self._check_connected()
    read = {
      1: self._packets.read1ByteTxRx,
      2: self._packets.read2ByteTxRx,
      4: self._packets.read4ByteTxRx,
    }[item.size]
    values, silent = {}, []
    for motor_id in self._ids if motor_ids is None else motor_ids:
      for _ in range(self._retries + 1):
        value, result, _ = self._call(read, motor_id, item.address)
        if result == sdk.COMM_SUCCESS:
          values[motor_id] = (
            table.to_signed(value, item.size) if item.signed else value
          )
          break
      else:
        silent.append(motor_id)
    if silent:
      raise MissingMotorError(
        f'motors {silent} did not answer reading address {item.address}',
        silent,
      )
    return values

  def read_bytes(self, motor_id: int, address: int, length: int) -> bytes:
    """Reads `length` raw bytes of a motor's control table from `address`.

    Raises:
      MissingMotorError: if the motor does not answer.
      DynamixelError: if it refuses the read (e.g. an Access error).
    """
    self._check_connected()
    for _ in range(self._retries + 1):
      data, result, error = self._call(
        self._packets.readTxRx, motor_id, address, length
      )
      if result != sdk.COMM_SUCCESS:
        continue
      if error & ~table.ALERT_BIT:
        raise DynamixelError(
          f'motor {motor_id} refused reading {length} bytes at address '
          f'{address}: {self._packets.getRxPacketError(error)}',
          [motor_id],
        )
      if len(data) == length:
        return bytes(data)
    raise MissingMotorError(
      f'motor {motor_id} did not answer reading address {address}',
      [motor_id],
    )

  def write_register(self, item: table.Item, values: dict[int, int]) -> None:
    """Writes one control-table item of several motors (individual writes).

    Raises:
      DynamixelError: naming motors that refuse or do not answer.
    """
    self._check_connected()
    write = {
      1: self._packets.write1ByteTxRx,
      2: self._packets.write2ByteTxRx,
      4: self._packets.write4ByteTxRx,
    }[item.size]
    failed = {}
    for motor_id, value in values.items():
      raw = table.to_unsigned(int(value), item.size)
      for _ in range(self._retries + 1):
        result, error = self._call(write, motor_id, item.address, raw)
        if result == sdk.COMM_SUCCESS and not error & ~table.ALERT_BIT:
          break
      else:
        failed[motor_id] = (
          self._packets.getRxPacketError(error)
          if result == sdk.COMM_SUCCESS
          else self._packets.getTxRxResult(result)
        )
    if failed:
      raise DynamixelError(
        f'writing address {item.address} failed: {failed}', list(failed)
      )

  def sync_read_register(self, item: table.Item) -> dict[int, int]:
    """Reads one item of every motor in a single sync-read transaction.

    Raises:
      MissingMotorError: naming motors that do not answer.
      DynamixelError: if the transaction keeps failing.
    """
    self._check_connected()
    reader = self._register_readers.get(item.address)
    if reader is None:
      reader = sdk.GroupSyncRead(
        self._port, self._packets, item.address, item.size
      )
      for motor_id in self._ids:
        reader.addParam(motor_id)
      self._register_readers[item.address] = reader
    for _ in range(self._retries + 1):
      result = self._call(lambda port: reader.txRxPacket())
      if result == sdk.COMM_SUCCESS and all(
        reader.isAvailable(i, item.address, item.size) for i in self._ids
      ):
        break
    else:
      silent = self._silent_motors(self._ids)
      if silent:
        raise MissingMotorError(f'motors {silent} stopped answering', silent)
      raise DynamixelError(
        f'reading address {item.address} failed: '
        f'{self._packets.getTxRxResult(result)}',
        self._ids,
      )
    values = {i: reader.getData(i, item.address, item.size) for i in self._ids}
    if item.signed:
      values = {i: table.to_signed(v, item.size) for i, v in values.items()}
    return values

  def hardware_errors(self, motor_ids=None) -> dict[int, int]:
    """Hardware Error Status of the motors that have one (bits, see table)."""
    if motor_ids is None:
      values = self.sync_read_register(table.HARDWARE_ERROR_STATUS)
    else:
      values = self.read_register(table.HARDWARE_ERROR_STATUS, motor_ids)
    return {i: bits for i, bits in values.items() if bits}

  def raise_on_hardware_errors(self, motor_ids=None) -> None:
    """Raises `MotorFaultError` if any of the motors has a hardware error."""
    errors = self.hardware_errors(motor_ids)
    if errors:
      raise MotorFaultError(
        f'hardware error: {describe_hardware_errors(errors)}; the motor '
        'needs a reboot (power cycle or Reboot instruction)',
        errors,
      )
