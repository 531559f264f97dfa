"""Register-level access of the Dynamixel client: any item of any motor.

Diagnostics (`scan`), health checks and configuration read and write single
control-table items, and torque is switched here; the control loop itself
uses only the client's state read and goal write. `DynamixelClient`
includes these methods.

Every reply is checked against what was asked (`packet_handler`): a late
reply to an earlier packet, which the SDK would take for the current one's
and decode into wrong numbers (or fail on with an IndexError), is dropped
with whatever else waits in the port, and the read is made again; a motor
that keeps answering so is named in a `DynamixelError`.

A failed ping or state read of the client is explained here as well: a
motor that sends no reply, a corrupted one, or one of the wrong length is
named as such, and a state read that got no reply at all while every motor
answers a ping right after is a stall of the whole bus, not a motor's fault.
"""

import time

from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel.errors import (
  DynamixelError,
  MissingMotorError,
  MotorFaultError,
  describe_hardware_errors,
)

try:
  import dynamixel_sdk as sdk
except ImportError:  # pragma: no cover - exercised without the extra
  sdk = None

_TORQUE_RETRY_INTERVAL_S = 0.05
# A release asks the motors to confirm their torque off for up to this long,
# all of them together.
RELEASE_CONFIRM_S = 0.5
_RELEASE_RETRY_INTERVAL_S = 0.02
# What the client's packet handler answers (beside the SDK's COMM_* results)
# for a status packet of the wrong length for its instruction.
COMM_WRONG_LENGTH = -3100
# A status packet, unstuffed: header (4 bytes), ID, length (2), instruction,
# error, parameters, CRC (2); the length counts instruction to CRC.
_ID, _LENGTH, _INSTRUCTION, _PARAMETERS = 4, 5, 7, 8
_STATUS_OVERHEAD = 4  # Instruction, error, CRC.
_PING_REPLY_SIZE = 3  # Model number (2), firmware version.


def _parameter_count(packet) -> int:
  return packet[_LENGTH] + (packet[_LENGTH + 1] << 8) - _STATUS_OVERHEAD


def _reply_size(txpacket) -> int | None:
  """Parameter bytes of the reply an instruction packet asks for (None:
  no reply, or not checked)."""
  if txpacket[_ID] == sdk.BROADCAST_ID:
    return None
  instruction = txpacket[_INSTRUCTION]
  if instruction == sdk.INST_READ:  # Parameters: address (2), length (2).
    return txpacket[_PARAMETERS + 2] + (txpacket[_PARAMETERS + 3] << 8)
  if instruction == sdk.INST_PING:
    return _PING_REPLY_SIZE
  if instruction in (
    sdk.INST_WRITE,
    sdk.INST_REG_WRITE,
    sdk.INST_REBOOT,
    sdk.INST_CLEAR,
    sdk.INST_FACTORY_RESET,
  ):
    return 0
  return None


def packet_handler():
  """The SDK's Protocol 2.0 packet handler, checking every reply's length.

  A read's reply must carry exactly the bytes asked for (in a sync read,
  each motor's), a ping's three, a write's none; a refusal (an error
  status) may carry none. Any other reply, most often a late one to an
  earlier packet, drains the port, and the transaction answers
  `COMM_WRONG_LENGTH`; the handler's `bad_reply` then holds (motor ID,
  parameter bytes received, bytes expected).
  """

  class PacketHandler(sdk.Protocol2PacketHandler):
    bad_reply: tuple[int, int, int] | None = None
    _received = None  # The status packet read last.

    def rxPacket(self, port, fast_option):  # noqa: N802 (SDK method name)
      packet, result = super().rxPacket(port, fast_option)
      self._received = packet
      return packet, result

    def txRxPacket(self, port, txpacket):  # noqa: N802 (SDK method name)
      packet, result, error = super().txRxPacket(port, txpacket)
      expected = _reply_size(txpacket)
      if result == sdk.COMM_SUCCESS and expected is not None:
        received = _parameter_count(packet)
        refusal = received == 0 and error & ~table.ALERT_BIT
        if received != expected and not refusal:
          result = self._wrong_length(port, packet, expected)
      return packet, result, error

    def readRx(self, port, dxl_id, length):  # noqa: N802 (a sync read's)
      data, result, error = super().readRx(port, dxl_id, length)
      packet = self._received
      if result == sdk.COMM_SUCCESS and _parameter_count(packet) != length:
        return [], self._wrong_length(port, packet, length), error
      return data, result, error

    def getTxRxResult(self, result):  # noqa: N802 (SDK method name)
      if result == COMM_WRONG_LENGTH:
        return '[TxRxResult] Status packet of the wrong length!'
      return super().getTxRxResult(result)

    def _wrong_length(self, port, packet, expected: int) -> int:
      port.clearPort()
      self.bad_reply = (packet[_ID], _parameter_count(packet), expected)
      return COMM_WRONG_LENGTH

  return PacketHandler()


class RegisterAccess:
  """Reads and writes of single control-table items, and torque switching
  (a client's part).

  Relies on the client's connection: `_call`, `_packets` (a
  `packet_handler`), `_port`, `_ids`, `_retries`, `_device_path`,
  `_register_readers`, `_check_connected`, `_ping_result` and
  `_bus_silent`.
  """

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

  def read_register(self, item: table.Item, motor_ids=None) -> dict[int, int]:
    """Reads one control-table item of each motor (individual reads).

    Returns:
      Motor ID -> value (signed items decoded).

    Raises:
      MissingMotorError: naming motors that do not answer.
      DynamixelError: naming a motor that refuses the read, or whose replies
        keep having the wrong length.
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
        value, result, error = self._call(read, motor_id, item.address)
        if result == sdk.COMM_SUCCESS:
          break
      else:
        if result == COMM_WRONG_LENGTH:
          raise self._wrong_replies(item.address)
        silent.append(motor_id)
        continue
      if error & ~table.ALERT_BIT:
        raise self._refused(motor_id, item.address, error)
      values[motor_id] = (
        table.to_signed(value, item.size) if item.signed else value
      )
    if silent:
      raise MissingMotorError(
        f'motors {silent} did not answer reading address {item.address} '
        f'on {self._device_path}',
        silent,
      )
    return values

  def read_bytes(self, motor_id: int, address: int, length: int) -> bytes:
    """Reads `length` raw bytes of a motor's control table from `address`.

    Raises:
      MissingMotorError: if the motor does not answer.
      DynamixelError: if it refuses the read (e.g. an Access error), or its
        replies keep having the wrong length.
    """
    self._check_connected()
    for _ in range(self._retries + 1):
      data, result, error = self._call(
        self._packets.readTxRx, motor_id, address, length
      )
      if result != sdk.COMM_SUCCESS:
        continue
      if error & ~table.ALERT_BIT:
        raise self._refused(motor_id, address, error)
      if len(data) == length:
        return bytes(data)
    if result == COMM_WRONG_LENGTH:
      raise self._wrong_replies(address)
    raise MissingMotorError(
      f'motor {motor_id} did not answer reading address {address} on '
      f'{self._device_path}',
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
      DynamixelError: naming a motor whose replies keep having the wrong
        length, or if the transaction keeps failing.
    """
    self._check_connected()
    key = (item.address, item.size)
    for _ in range(self._retries + 1):
      reader, result = self._call(lambda port: self._sync_read(port, key))
      if result == sdk.COMM_SUCCESS:
        break
    else:
      if result == COMM_WRONG_LENGTH:
        raise self._wrong_replies(item.address)
      silent = self._silent_motors(self._ids)
      if silent:
        raise MissingMotorError(
          f'motors {silent} stopped answering on {self._device_path}', silent
        )
      raise DynamixelError(
        f'reading address {item.address} on {self._device_path} failed: '
        f'{self._packets.getTxRxResult(result)}',
        self._ids,
      )
    values = {i: reader.getData(i, item.address, item.size) for i in self._ids}
    if item.signed:
      values = {i: table.to_signed(v, item.size) for i, v in values.items()}
    return values

  def _sync_read(self, port, key: tuple[int, int]):
    """(reader, SDK result) of one sync read of (address, size)."""
    reader = self._register_readers.get(key)
    if reader is None:
      reader = sdk.GroupSyncRead(port, self._packets, *key)
      for motor_id in self._ids:
        reader.addParam(motor_id)
      self._register_readers[key] = reader
    return reader, reader.txRxPacket()

  def _refused(self, motor_id: int, address: int, error: int):
    return DynamixelError(
      f'motor {motor_id} refused reading address {address} on '
      f'{self._device_path}: {self._packets.getRxPacketError(error)}',
      [motor_id],
    )

  def _wrong_replies(self, address: int) -> DynamixelError:
    """The error naming the motor whose replies kept the wrong length."""
    motor_id, received, expected = self._packets.bad_reply
    return DynamixelError(
      f'motor {motor_id} answered reading address {address} on '
      f'{self._device_path} with {received} bytes instead of {expected}, '
      f'{self._retries + 1} times in a row, the port drained each time '
      '(late replies to earlier packets?)',
      [motor_id],
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

  def confirm_torque_off(self, motor_ids) -> list[int]:
    """Turns the motors' torque off, asking again those that do not confirm
    (a motor may miss a few packets, then answer) until `RELEASE_CONFIRM_S`
    has passed for all of them together; returns those that never did."""
    deadline = time.monotonic() + RELEASE_CONFIRM_S
    unconfirmed = list(motor_ids)
    while True:
      unconfirmed = [i for i in unconfirmed if not self._torque_off_once(i)]
      if not unconfirmed or time.monotonic() >= deadline:
        return unconfirmed
      time.sleep(_RELEASE_RETRY_INTERVAL_S)

  def _torque_off_once(self, motor_id: int) -> bool:
    result, error = self._call(
      self._packets.write1ByteTxRx, motor_id, table.TORQUE_ENABLE.address, 0
    )
    return result == sdk.COMM_SUCCESS and not error & ~table.ALERT_BIT

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

  # --- What a failed read means ----------------------------------------------

  @staticmethod
  def _is_silent(result: int) -> bool:
    """Whether an SDK result means that no reply came (not a bad one)."""
    return result not in (sdk.COMM_RX_CORRUPT, COMM_WRONG_LENGTH)

  @staticmethod
  def _ping_failure(result: int, bad_reply: tuple | None) -> str:
    """How a ping without a valid reply failed, to follow 'motor N': from
    its SDK result and the packet handler's `bad_reply`."""
    if result == COMM_WRONG_LENGTH:
      _, received, expected = bad_reply
      return (
        f'answered a ping with {received} bytes instead of {expected} (a late '
        'reply to an earlier packet?)'
      )
    if result == sdk.COMM_RX_CORRUPT:
      return 'answered a ping with a corrupted reply (bad checksum)'
    return 'does not answer'

  def _connect_failure(self, failed: dict[int, tuple]) -> str:
    """The message of `connect` for the motors that failed their pings
    (motor ID -> (result, bad reply), as `_failed_pings` gives)."""
    path = self._device_path
    silent = [i for i, (result, _) in failed.items() if self._is_silent(result)]
    if len(silent) == len(failed):
      return (
        f'motors {silent} do not answer on {path}; check wiring, power, IDs '
        'and baud rate'
      )
    return f'no valid reply to a ping on {path}: ' + '; '.join(
      f'motor {motor_id} {self._ping_failure(*failure)}'
      for motor_id, failure in failed.items()
    )

  def _silent_motors(self, motor_ids) -> list[int]:
    """The motors of `motor_ids` that send no reply to a ping (a motor
    that sends a bad one is not silent)."""
    silent = []
    for motor_id in motor_ids:
      model, result = self._ping_result(motor_id)
      if model is None and self._is_silent(result):
        silent.append(motor_id)
    return silent

  def _read_failure(self, failures) -> DynamixelError:
    """The error that names who failed a state read, and how."""
    path = self._device_path
    results = {result for _, result, _ in failures}
    wrong = {bad[0] for _, _, bad in failures if bad}
    if results == {COMM_WRONG_LENGTH} and len(wrong) == 1:
      motor_id, received, expected = failures[-1][2]
      return DynamixelError(
        f'motor {motor_id} answered the state read on {path} with {received} '
        f'bytes instead of {expected}, {len(failures)} times in a row, the '
        'port drained each time (late replies to earlier packets?)',
        [motor_id],
      )
    corrupted = sorted(
      {i for i, result, _ in failures if result == sdk.COMM_RX_CORRUPT}
    )
    if len(corrupted) == 1 and results == {sdk.COMM_RX_CORRUPT}:
      return DynamixelError(
        f'motor {corrupted[0]} answered with corrupted replies (bad '
        f'checksum) {len(failures)} times in a row on {path}: check its '
        'cable and connectors',
        corrupted,
      )
    # One ping each, no retry: a silent bus is recognized in well under 1 s.
    failed = self._failed_pings(self._ids)
    if len(failed) == len(self._ids) and all(
      self._is_silent(result) for result, _ in failed.values()
    ):
      self._bus_silent = True
      return MissingMotorError(
        f'no motor answers on {path}: check power and cable', list(failed)
      )
    # The read timed out before its first reply every time: if the motors
    # that missed a ping answer a second, the whole bus was late.
    nothing = all(
      result == sdk.COMM_RX_TIMEOUT and short == self._ids[0]
      for short, result, _ in failures
    )
    if nothing and failed:
      failed = self._failed_pings(failed)
    if nothing and not failed:
      return DynamixelError(
        f'no motor answered the state read on {path}, {len(failures)} times '
        'in a row, yet every motor answered a ping right after: the whole '
        'bus stalled (replies late past the deadline: a busy computer, or a '
        'slow USB adapter), not one motor',
        self._ids,
      )
    return self._ping_failures(failures, failed, corrupted)

  def _failed_pings(self, motor_ids) -> dict[int, tuple]:
    """Motor ID -> (SDK result, the handler's `bad_reply`) of the motors
    of `motor_ids` that gave no valid reply to one ping each."""
    failed = {}
    for motor_id in motor_ids:
      model, result = self._ping_result(motor_id, attempts=1)
      if model is None:
        failed[motor_id] = result, self._packets.bad_reply
    return failed

  def _ping_failures(self, failures, failed, corrupted) -> DynamixelError:
    """The error of a failed state read after the motors were pinged:
    `failed` as `_failed_pings` gives; `corrupted` lists the motors whose
    state replies were corrupted."""
    path = self._device_path
    silent = [i for i, (result, _) in failed.items() if self._is_silent(result)]
    if silent:
      return MissingMotorError(
        f'motors {silent} stopped answering on {path}', silent
      )
    garbled = [
      i for i, (result, _) in failed.items() if result == sdk.COMM_RX_CORRUPT
    ]
    corrupted = sorted(set(corrupted) | set(garbled))
    if corrupted:
      return DynamixelError(
        f'motors {corrupted} answered with corrupted replies (bad checksum) '
        f'on {path}: check their cables and connectors',
        corrupted,
      )
    if failed:
      return DynamixelError(
        f'reading the motors on {path} failed: '
        + '; '.join(
          f'motor {i} {self._ping_failure(*f)}' for i, f in failed.items()
        ),
        list(failed),
      )
    result = failures[-1][1]
    return DynamixelError(
      f'reading motors {list(self._ids)} on {path} failed: '
      f'{self._packets.getTxRxResult(result)}',
      self._ids,
    )
