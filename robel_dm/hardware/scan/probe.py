"""Reading a Dynamixel bus: which motors answer, what their registers hold.

`scan` finds the motors (pings, and optionally a Broadcast Ping that covers
every ID) and reads each into a `MotorReport`, without touching torque.
"""

from collections.abc import Iterable
import contextlib
import dataclasses

from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table

MAX_ID = 252
ALL_IDS = tuple(range(MAX_ID + 1))
US_PER_RETURN_DELAY_UNIT = 2

# The two blocks a motor is read in: 0..70 (EEPROM and the RAM items up to
# Hardware Error Status) and 132..146 (present position to temperature).
_BLOCKS = (
  (table.MODEL_NUMBER.address, table.HARDWARE_ERROR_STATUS.address + 1),
  (table.PRESENT_POSITION.address, table.PRESENT_TEMPERATURE.address + 1),
)
_ITEMS = {
  'firmware': table.FIRMWARE_VERSION,
  'baud_register': table.BAUD_RATE,
  'return_delay_time': table.RETURN_DELAY_TIME,
  'operating_mode': table.OPERATING_MODE,
  'max_position_limit': table.MAX_POSITION_LIMIT,
  'min_position_limit': table.MIN_POSITION_LIMIT,
  'torque_enable': table.TORQUE_ENABLE,
  'status_return_level': table.STATUS_RETURN_LEVEL,
  'hardware_error': table.HARDWARE_ERROR_STATUS,
  'position': table.PRESENT_POSITION,
  'input_voltage_raw': table.PRESENT_INPUT_VOLTAGE,
  'temperature': table.PRESENT_TEMPERATURE,
}


@dataclasses.dataclass(frozen=True)
class MotorReport:
  """What one motor reports; register fields are None if unreadable.

  Attributes:
    id: Dynamixel ID.
    model_number: from the ping.
    firmware: Firmware Version.
    position: Present Position, ticks.
    temperature: Present Temperature, deg C.
    input_voltage_raw: Present Input Voltage, 0.1 V.
    operating_mode: Operating Mode register.
    baud_register: Baud Rate register (0..7).
    return_delay_time: Return Delay Time register, 2 us.
    status_return_level: Status Return Level (0..2).
    min_position_limit: Min Position Limit, ticks.
    max_position_limit: Max Position Limit, ticks.
    torque_enable: Torque Enable (0 or 1).
    hardware_error: Hardware Error Status bits.
    read_error: why the registers could not be read (None if they were).
  """

  id: int
  model_number: int
  firmware: int | None = None
  position: int | None = None
  temperature: int | None = None
  input_voltage_raw: int | None = None
  operating_mode: int | None = None
  baud_register: int | None = None
  return_delay_time: int | None = None
  status_return_level: int | None = None
  min_position_limit: int | None = None
  max_position_limit: int | None = None
  torque_enable: int | None = None
  hardware_error: int | None = None
  read_error: str | None = None

  @property
  def readable(self) -> bool:
    return self.read_error is None

  @property
  def model_name(self) -> str | None:
    """The model's name, None for an unknown model number."""
    model = table.MODELS.get(self.model_number)
    return model[0] if model else None

  @property
  def position_rad(self) -> float | None:
    """Motor angle, rad (ticks * 2 pi / 4096)."""
    if self.position is None:
      return None
    return self.position * table.RADIANS_PER_TICK

  @property
  def input_voltage(self) -> float | None:
    """Input voltage, V."""
    if self.input_voltage_raw is None:
      return None
    return self.input_voltage_raw * table.VOLTS_PER_UNIT

  @property
  def return_delay_us(self) -> int | None:
    if self.return_delay_time is None:
      return None
    return self.return_delay_time * US_PER_RETURN_DELAY_UNIT

  @property
  def baud_rate(self) -> int | None:
    """Bits per second the Baud Rate register selects (None if unknown)."""
    return table.BAUD_RATES.get(self.baud_register)

  @property
  def torque_enabled(self) -> bool | None:
    return None if self.torque_enable is None else bool(self.torque_enable)

  @property
  def hardware_error_names(self) -> list[str]:
    return table.hardware_error_names(self.hardware_error or 0)


def open_bus(
  device_path: str,
  baud_rate: int = table.DEFAULT_BAUD_RATE,
  retries: int = 2,
) -> dynamixel.DynamixelClient:
  """Opens a port for probing (no motor is required; torque is untouched).

  Raises:
    dynamixel.DynamixelError: if the device cannot be opened.
    ValueError: for a baud rate that Dynamixel servos do not support.
  """
  client = dynamixel.DynamixelClient(
    device_path, ALL_IDS, baud_rate=baud_rate, retries=retries
  )
  client.connect(check_motors=False)
  return client


def find_motors(
  client: dynamixel.DynamixelClient,
  ids: Iterable[int] = (),
  all_ids: bool = False,
) -> dict[int, int]:
  """Finds which motors answer.

  Args:
    client: a connected client.
    ids: IDs to ping one by one.
    all_ids: also find every other ID with one Broadcast Ping (~0.8 s, where
      pinging 253 absent IDs one by one would take 253 timeouts).

  Returns:
    Motor ID -> model number, by ID.
  """
  found = {}
  if all_ids:
    found = {i: model for i, (model, _) in client.broadcast_ping().items()}
  for motor_id in ids:
    if motor_id not in found:
      with contextlib.suppress(dynamixel.MissingMotorError):
        found[motor_id] = client.ping(motor_id)
  return dict(sorted(found.items()))


def _decode(item: table.Item, raw: bytes) -> int:
  value = int.from_bytes(raw, 'little')
  return table.to_signed(value, item.size) if item.signed else value


def _read_fields(client, motor_id: int) -> dict[str, int]:
  """Reads the report's registers in two block reads.

  Falls back to one read per item if a block read is refused (firmware
  that does not allow reading across reserved addresses).
  """
  try:
    blocks = [
      (start, client.read_bytes(motor_id, start, end - start))
      for start, end in _BLOCKS
    ]
  except dynamixel.MissingMotorError:
    raise
  except dynamixel.DynamixelError:
    return {
      field: client.read_register(item, [motor_id])[motor_id]
      for field, item in _ITEMS.items()
    }
  fields = {}
  for field, item in _ITEMS.items():
    for start, data in blocks:
      offset = item.address - start
      if offset >= 0 and offset + item.size <= len(data):
        fields[field] = _decode(item, data[offset : offset + item.size])
        break
  return fields


def read_motor(
  client: dynamixel.DynamixelClient, motor_id: int, model_number: int
) -> MotorReport:
  """Reads one motor's registers into a report (never raises for the motor).

  A motor that answers pings but not reads (Status Return Level 0, or it
  went away) gets a report with `read_error` set.
  """
  try:
    fields = _read_fields(client, motor_id)
  except dynamixel.DynamixelError as error:
    return MotorReport(motor_id, model_number, read_error=str(error))
  return MotorReport(motor_id, model_number, **fields)


def scan(
  client_or_device: dynamixel.DynamixelClient | str,
  ids: Iterable[int] = (),
  all_ids: bool = False,
  baud_rate: int = table.DEFAULT_BAUD_RATE,
) -> list[MotorReport]:
  """Finds the motors and reads each.

  Args:
    client_or_device: a connected client, or a device path to open (at
      `baud_rate`) for the scan.
    ids: IDs to ping one by one.
    all_ids: also find every other ID (Broadcast Ping).
    baud_rate: bits per second, when a device path is given.

  Returns:
    One report per motor found, by ID.

  Raises:
    dynamixel.DynamixelError: if a device path cannot be opened.
  """
  if isinstance(client_or_device, str):
    client = open_bus(client_or_device, baud_rate)
    try:
      return scan(client, ids, all_ids)
    finally:
      client.disconnect()
  client = client_or_device
  found = find_motors(client, ids, all_ids)
  return [read_motor(client, i, model) for i, model in found.items()]
