"""Register-level access of the Dynamixel client: any item of any motor.

Diagnostics (`scan`), health checks and configuration read and write single
control-table items; the control loop itself uses only the client's state
read and goal write. `DynamixelClient` includes these methods.
"""

from robel_dm.hardware import control_table as table
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


class RegisterAccess:
  """Reads and writes of single control-table items (a client's part).

  Relies on the client's connection: `_call`, `_packets`, `_port`, `_ids`,
  `_retries`, `_check_connected` and `_silent_motors`.
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
