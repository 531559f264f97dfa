"""A virtual X430 servo: its control table and the firmware's rules.

`VirtualServo` holds a full X430 control table (addresses 0..661) and
applies the firmware's rules (`registers`) to reads and writes: read-only
items, the EEPROM lock while torque is on, item lengths, ranges and limits,
hardware errors with shutdown, Reg Write/Action, Reboot, Factory Reset and
indirect addressing.

Behaviour the e-manual leaves open, chosen here (docs/dynamixel.md marks these
unverified): a Goal Position outside the position limits is refused with
error 6 (Data Limit); an attempt to enable torque during a hardware-error
shutdown is answered with the alert bit and no error number. Not modelled:
profiles, Drive Mode, homing offset and the bus watchdog.
"""

import collections
from collections.abc import Iterable
import operator
import threading
import time

from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel import protocol
from robel_dm.hardware.dynamixel.protocol import Error
from robel_dm.hardware.virtual import registers

DEFAULT_MODEL_NUMBER = 1040  # XH430-V350, as on ROBEL's robots.
DEFAULT_FIRMWARE = 46
DEFAULT_TEMPERATURE = 35  # deg C.
_CENTER_TICKS = 2_048


class VirtualServo:
  """One X430 servo: its control table and the firmware's rules.

  The constructor's table is that of a servo configured for ROBEL: ID
  `motor_id`, 1 Mbps, Return Delay Time 0, Status Return Level 2, position
  mode, torque off, at the center position (2048). Factory Reset restores
  the factory values instead (ID 1, 57,600 bps, Return Delay Time 250).

  Methods take `lock`; a `Bus` replaces it with its own, so that other
  threads can use the helpers while the bus serves packets.

  Attributes:
    table: the control table, addresses 0..661 (raw bytes).
    lock: serializes access (an RLock).
    counters: instruction code -> packets this servo received (a Counter;
      `Instruction` members index it). Packets lost to `Faults` (absent,
      muted) or sent at another baud rate are not counted.
    crc_errors: packets addressed to this servo that failed their CRC.
  """

  def __init__(
    self,
    motor_id: int,
    model_number: int = DEFAULT_MODEL_NUMBER,
    firmware: int = DEFAULT_FIRMWARE,
  ):
    """Initializes the servo.

    Args:
      motor_id: Dynamixel ID, 0..252.
      model_number: e.g. 1030 (XM430-W210) or 1040 (XH430-V350); other
        numbers get XM430-W210 limits.
      firmware: Firmware Version register.

    Raises:
      ValueError: for an invalid ID, model number or firmware version.
    """
    if not 0 <= motor_id <= protocol.MAX_ID:
      raise ValueError(f'motor ID must be 0..{protocol.MAX_ID}: {motor_id}')
    if not 0 <= model_number <= 0xFFFF or not 0 <= firmware <= 0xFF:
      raise ValueError(f'bad model {model_number} or firmware {firmware}')
    self._model_number = model_number
    self._firmware = firmware
    self._defaults = registers.MODEL_DEFAULTS.get(
      model_number, registers.MODEL_DEFAULTS[1030]
    )
    self.lock = threading.RLock()
    self.table = self._initial_table(motor_id, factory=False)
    self.counters: collections.Counter[int] = collections.Counter()
    self.crc_errors = 0
    self._registered: tuple[int, bytes] | None = None
    # A current the motor draws whatever its driver says (a stall), units.
    self._injected_current: int | None = None

  def __repr__(self) -> str:
    return (
      f'VirtualServo(id={self.motor_id}, model={self._model_number}, '
      f'torque={int(self.torque_enabled)}, goal={self.goal_position}, '
      f'position={self.present_position})'
    )

  def _initial_table(self, motor_id: int, factory: bool) -> bytearray:
    values = {
      table.MODEL_NUMBER: self._model_number,
      table.FIRMWARE_VERSION: self._firmware,
      table.ID: 1 if factory else motor_id,
      table.BAUD_RATE: 1 if factory else 3,  # 57,600 / 1,000,000 bps.
      table.RETURN_DELAY_TIME: 250 if factory else 0,
      table.OPERATING_MODE: table.POSITION_MODE,
      table.SECONDARY_ID: 255,
      table.PROTOCOL_TYPE: 2,
      table.MOVING_THRESHOLD: 10,
      table.TEMPERATURE_LIMIT: 80,
      table.MAX_VOLTAGE_LIMIT: self._defaults.max_voltage_limit,
      table.MIN_VOLTAGE_LIMIT: self._defaults.min_voltage_limit,
      table.PWM_LIMIT: 885,
      table.CURRENT_LIMIT: self._defaults.current_limit,
      table.VELOCITY_LIMIT: self._defaults.velocity_limit,
      table.MAX_POSITION_LIMIT: 4_095,
      table.MIN_POSITION_LIMIT: 0,
      table.SHUTDOWN: 0x34,  # Overheating, electrical shock, overload.
      table.STATUS_RETURN_LEVEL: 2,
      table.VELOCITY_I_GAIN: 1_920,
      table.VELOCITY_P_GAIN: 100,
      table.POSITION_P_GAIN: 800,
      table.GOAL_POSITION: _CENTER_TICKS,
      table.PRESENT_POSITION: _CENTER_TICKS,
      table.POSITION_TRAJECTORY: _CENTER_TICKS,
      table.PRESENT_INPUT_VOLTAGE: self._defaults.input_voltage,
      table.PRESENT_TEMPERATURE: DEFAULT_TEMPERATURE,
    }
    for data_address, address_item in registers.INDIRECT.items():
      values[address_item] = data_address  # Each points at its own data.
    buffer = bytearray(registers.SIZE)
    for item, value in values.items():
      raw = registers.encode(item, value)
      buffer[item.address : item.address + item.size] = raw
    return buffer

  # --- Registers -------------------------------------------------------------

  def get(self, item: table.Item) -> int:
    """The value of `item` (signed items as signed)."""
    with self.lock:
      raw = self.table[item.address : item.address + item.size]
      return registers.decode(raw, item)

  def set(self, item: table.Item, value: int) -> None:
    """Stores `value` in `item` without any firmware check.

    For drivers and tests; packets go through `write`.

    Raises:
      ValueError: if the value does not fit the item's size.
      TypeError: for a non-integer value (e.g. a float).
    """
    raw = registers.encode(item, operator.index(value))
    with self.lock:
      self.table[item.address : item.address + item.size] = raw

  @property
  def motor_id(self) -> int:
    return self.table[table.ID.address]  # One byte: no lock needed.

  @property
  def model_number(self) -> int:
    return self.get(table.MODEL_NUMBER)

  @property
  def firmware(self) -> int:
    return self.get(table.FIRMWARE_VERSION)

  @property
  def baud_rate(self) -> int:
    """The servo's bit rate (from its Baud Rate register)."""
    return table.BAUD_RATES[self.table[table.BAUD_RATE.address]]

  @property
  def operating_mode(self) -> int:
    return self.get(table.OPERATING_MODE)

  @property
  def status_return_level(self) -> int:
    return self.table[table.STATUS_RETURN_LEVEL.address]

  @property
  def torque_enabled(self) -> bool:
    return bool(self.table[table.TORQUE_ENABLE.address])

  @property
  def goal_position(self) -> int:
    """The last Goal Position accepted, ticks (signed)."""
    return self.get(table.GOAL_POSITION)

  @property
  def goal_velocity(self) -> int:
    return self.get(table.GOAL_VELOCITY)

  @property
  def goal_current(self) -> int:
    return self.get(table.GOAL_CURRENT)

  @property
  def present_position(self) -> int:
    return self.get(table.PRESENT_POSITION)

  @property
  def present_velocity(self) -> int:
    return self.get(table.PRESENT_VELOCITY)

  @property
  def present_current(self) -> int:
    return self.get(table.PRESENT_CURRENT)

  @property
  def hardware_error(self) -> int:
    """The latched Hardware Error Status bits (0: none)."""
    return self.table[table.HARDWARE_ERROR_STATUS.address]

  @property
  def in_shutdown(self) -> bool:
    """Whether a latched error is one of the Shutdown register's."""
    with self.lock:
      return bool(self.hardware_error & self.get(table.SHUTDOWN))

  @property
  def packets_received(self) -> int:
    """Instruction packets this servo received (all of `counters`)."""
    return sum(self.counters.values())

  def set_present(
    self, position_ticks: int, velocity_units: int = 0, current_units: int = 0
  ) -> None:
    """Sets the measured state (what a motor driver computes).

    Args:
      position_ticks: Present Position, ticks (signed).
      velocity_units: Present Velocity, units of 0.229 rpm (signed).
      current_units: Present Current, model units (signed).

    Raises:
      ValueError: if a value does not fit its register.
      TypeError: for non-integer values.
    """
    with self.lock:
      if self._injected_current is not None:
        current_units = self._injected_current
      self.set(table.PRESENT_POSITION, position_ticks)
      self.set(table.PRESENT_VELOCITY, velocity_units)
      self.set(table.PRESENT_CURRENT, current_units)
      self.set(table.POSITION_TRAJECTORY, position_ticks)
      self.set(table.VELOCITY_TRAJECTORY, velocity_units)
      moving = abs(velocity_units) > self.get(table.MOVING_THRESHOLD)
      self.set(table.MOVING, int(moving))

  def inject_current(self, current_units: int | None) -> None:
    """Makes the motor report this Present Current (model units), as a
    stalled or shorted motor would, until called with None.

    Raises:
      ValueError: if the value does not fit the register.
    """
    with self.lock:
      self._injected_current = current_units
      if current_units is not None:
        self.set(table.PRESENT_CURRENT, current_units)

  # --- Hardware errors -------------------------------------------------------

  def inject_hardware_error(self, bits: int) -> None:
    """Latches hardware-error bits in register 70, as the firmware would.

    If any bit is in the Shutdown register, torque goes off and cannot be
    turned on again until a Reboot. Every status packet carries the alert
    bit until then.

    Args:
      bits: Hardware Error Status bits (control_table.HARDWARE_ERRORS).

    Raises:
      ValueError: for no bits or unknown bits.
    """
    known = sum(table.HARDWARE_ERRORS)
    if not bits or bits & ~known:
      raise ValueError(f'hardware error bits must be within 0x{known:02x}')
    with self.lock:
      self.set(table.HARDWARE_ERROR_STATUS, self.hardware_error | bits)
      if self.in_shutdown:
        self.set(table.TORQUE_ENABLE, 0)

  def status_error(self, result: int) -> int:
    """The error byte of a status packet reporting `result`."""
    return result | table.ALERT_BIT if self.hardware_error else result

  # --- Instructions ----------------------------------------------------------

  def read(self, address: int, length: int) -> tuple[int, bytes]:
    """Executes a Read.

    Returns:
      (error number, data); the data is empty on error. Reserved addresses
      read as 0; Indirect Data reads the address it points at.
    """
    with self.lock:
      end = address + length
      if length <= 0:
        return Error.DATA_LENGTH, b''
      if address < 0 or end > registers.SIZE:
        return Error.ACCESS, b''
      tick = int(time.monotonic() * 1000) % registers.REALTIME_TICK_PERIOD
      self.table[registers.TICK_SLICE] = tick.to_bytes(2, 'little')
      data = self.table[address:end]
      for data_address in self._indirect_data_in(address, end):
        target = self.get(registers.INDIRECT[data_address])
        data[data_address - address] = (
          self.table[target] if target < registers.SIZE else 0
        )
      return Error.NONE, bytes(data)

  def write(self, address: int, data: bytes | bytearray) -> int:
    """Executes a Write.

    Returns:
      The error number: 0, or Access (read-only or reserved address, EEPROM
      while torque is on), Data Length (partial item), Data Range (outside
      the item's range) or Data Limit (outside a limit register). Nothing is
      written on error. Enabling torque during a shutdown is ignored and
      answered with 0 (the status packet carries the alert bit).
    """
    with self.lock:
      result, stores = self._check_write(address, bytes(data))
      if result:
        return result
      for target, raw in stores:
        if (
          target == table.TORQUE_ENABLE.address and raw[0] and self.in_shutdown
        ):
          continue
        self.table[target : target + len(raw)] = raw
      return Error.NONE

  def reg_write(self, address: int, data: bytes | bytearray) -> int:
    """Executes a Reg Write: checks and stores the write for Action."""
    with self.lock:
      result, _ = self._check_write(address, bytes(data))
      if result:
        return result
      self._registered = (address, bytes(data))
      self.set(table.REGISTERED_INSTRUCTION, 1)
      return Error.NONE

  def action(self) -> int:
    """Executes an Action: applies the registered write.

    Returns:
      The write's error number; Instruction error if nothing is registered.
    """
    with self.lock:
      if self._registered is None:
        return Error.INSTRUCTION
      address, data = self._registered
      self._registered = None
      self.set(table.REGISTERED_INSTRUCTION, 0)
      return self.write(address, data)

  def reboot(self) -> None:
    """Reboots: RAM back to its power-on values, hardware errors cleared.

    The EEPROM area, the Indirect Address entries and the measured state
    stay; Goal Position becomes the present position.
    """
    with self.lock:
      self._reset(self._initial_table(self.motor_id, factory=False), False)

  def factory_reset(self, option: int) -> int:
    """Executes a Factory Reset (and the reboot that follows).

    Args:
      option: protocol.RESET_ALL, RESET_ALL_BUT_ID or
        RESET_ALL_BUT_ID_AND_BAUD.

    Returns:
      The error number (Data Range for an unknown option).
    """
    options = (
      protocol.RESET_ALL,
      protocol.RESET_ALL_BUT_ID,
      protocol.RESET_ALL_BUT_ID_AND_BAUD,
    )
    if option not in options:
      return Error.DATA_RANGE
    with self.lock:
      motor_id, baud = self.motor_id, self.get(table.BAUD_RATE)
      fresh = self._initial_table(motor_id, factory=True)
      self._reset(fresh, True)
      if option != protocol.RESET_ALL:
        self.set(table.ID, motor_id)
      if option == protocol.RESET_ALL_BUT_ID_AND_BAUD:
        self.set(table.BAUD_RATE, baud)
      return Error.NONE

  def clear_multi_turn(self) -> int:
    """Executes Clear: brings the position back within one turn."""
    with self.lock:
      if self.get(table.MOVING):
        return Error.RESULT_FAIL
      turns = self.present_position // 4096
      if turns:
        self.set(table.PRESENT_POSITION, self.present_position - 4096 * turns)
        self.set(table.GOAL_POSITION, self.goal_position - 4096 * turns)
      return Error.NONE

  # --- Internals -------------------------------------------------------------

  def _reset(self, fresh: bytearray, factory: bool) -> None:
    """Loads the RAM area (`factory`: also the EEPROM area) from `fresh`.

    The measured state stays, and so do the Indirect Address entries unless
    `factory`; Goal Position becomes the present position.
    """
    keep = list(registers.MEASUREMENTS)
    if not factory:
      keep += registers.INDIRECT.values()
    saved = [(item, self.get(item)) for item in keep]
    start = 0 if factory else registers.RAM_START
    self.table[start:] = fresh[start:]
    for item, value in saved:
      self.set(item, value)
    self.set(table.GOAL_POSITION, self.present_position)
    self._registered = None

  @staticmethod
  def _indirect_data_in(start: int, end: int) -> list[int]:
    addresses = []
    for span in registers.INDIRECT_DATA_RANGES:
      if start < span.stop and end > span.start:
        addresses += range(max(start, span.start), min(end, span.stop))
    return addresses

  def _check_write(
    self, address: int, data: bytes
  ) -> tuple[int, list[tuple[int, bytes]]]:
    """Checks a write; returns (error number, [(address, bytes) to store])."""
    end = address + len(data)
    if not data:
      return Error.DATA_LENGTH, []
    if address < 0 or end > registers.SIZE:
      return Error.ACCESS, []
    torque_on = self.torque_enabled
    stores = []
    position = address
    while position < end:
      item = registers.ITEM_AT[position]
      if item is None:
        return Error.ACCESS, []
      if item.address != position or item.address + item.size > end:
        return Error.DATA_LENGTH, []
      raw = data[position - address : position - address + item.size]
      if position in registers.INDIRECT:
        target = self.get(registers.INDIRECT[position])
        target_item = (
          registers.ITEM_AT[target] if target < registers.SIZE else None
        )
        if target != position and (
          target_item is None
          or not target_item.writable
          or target in registers.INDIRECT
        ):
          return Error.ACCESS, []
        stores.append((target, raw))
      else:
        if not item.writable or (item.eeprom and torque_on):
          return Error.ACCESS, []
        result = self._check_value(item, registers.decode(raw, item))
        if result:
          return result, []
        stores.append((position, raw))
      position += item.size
    return Error.NONE, stores

  def _check_value(self, item: table.Item, value: int) -> int:
    bounds = registers.RANGES.get(item)
    if bounds is not None and not bounds[0] <= value <= bounds[1]:
      return Error.DATA_RANGE
    if item == table.OPERATING_MODE and value not in table.OPERATING_MODES:
      return Error.DATA_RANGE
    if item == table.CURRENT_LIMIT and value > self._defaults.current_limit:
      return Error.DATA_RANGE
    if item == table.GOAL_POSITION:
      mode = self.operating_mode
      if mode == table.POSITION_MODE:
        low = self.get(table.MIN_POSITION_LIMIT)
        high = self.get(table.MAX_POSITION_LIMIT)
        if not low <= value <= high:
          return Error.DATA_LIMIT
      elif (
        mode in registers.MULTI_TURN_MODES
        and abs(value) > registers.MULTI_TURN_GOAL_RANGE
      ):
        return Error.DATA_RANGE
    limit = registers.GOAL_LIMITS.get(item)
    if limit is not None and abs(value) > self.get(limit):
      return Error.DATA_LIMIT
    return Error.NONE


def make_servos(
  ids: Iterable[int],
  model_number: int = DEFAULT_MODEL_NUMBER,
  firmware: int = DEFAULT_FIRMWARE,
) -> list[VirtualServo]:
  """One `VirtualServo` per ID, all of the same model."""
  return [VirtualServo(i, model_number, firmware) for i in ids]
