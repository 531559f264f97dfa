"""A virtual chain of Dynamixel X-series servos on a pseudo-terminal.

The unmodified `dynamixel_sdk` (or any Protocol 2.0 client) opens
`PtyBusServer.device_path` as if it were `/dev/ttyUSB0` and exchanges real
packets with it (docs/dynamixel.md section 4):

  servos = make_servos([10, 11, 12])
  with PtyBusServer(Bus(servos)) as server:
    port = dynamixel_sdk.PortHandler(server.device_path)
    ...

* `VirtualServo` holds a full X430 control table (addresses 0..661) and
  applies the firmware's rules to reads and writes: read-only items, the
  EEPROM lock while torque is on, item lengths, ranges and limits, hardware
  errors with shutdown, Reg Write/Action, Reboot, Factory Reset and indirect
  addressing.
* `Bus` executes instruction packets on the servos: Ping, Read, Write, Reg
  Write, Action, Factory Reset, Reboot, Clear, Sync/Bulk Read and Write, and
  Fast Sync/Bulk Read, with the Status Return Level and broadcast rules.
  A `Driver` moves the motors (`IdealDriver` by default; a physics
  simulation can take its place), and `Faults` injects communication
  failures at runtime.
* `PtyBusServer` serves a bus on a pseudo-terminal from a daemon thread.

Run `python -m robel_dm.hardware.virtual_bus --robot=dclaw` to serve a
robot's motors from the command line; it prints the device path.

Behaviour the e-manual leaves open, chosen here (docs/dynamixel.md marks these
unverified): an instruction with a bad CRC is answered with error 3, a
Goal Position outside the position limits with error 6 (Data Limit), an
attempt to enable torque during a hardware-error shutdown with the alert bit
and no error number; the reply to Reboot and Factory Reset describes the
state before the reset; malformed parameters give error 2 (Instruction).
Not modelled: wire timing and Return Delay Time (replies are immediate),
profiles, Drive Mode, homing offset, the bus watchdog, and any dynamics
beyond what the driver does.
"""

import collections
from collections.abc import Callable, Iterable, Mapping, Sequence
import contextlib
import dataclasses
import errno
import logging
import math
import operator
import os
import select
import signal
import sys
import termios
import threading
import time
import tty
from typing import Protocol

from robel_dm.hardware import config, protocol
from robel_dm.hardware import control_table as table
from robel_dm.hardware.protocol import Error, Instruction

_SIZE = table.CONTROL_TABLE_SIZE

# Indirect Data address -> the Indirect Address item that redirects it.
_INDIRECT = {
  table.indirect_data(n).address: table.indirect_address(n)
  for n in range(1, table.INDIRECT_ENTRIES + 1)
}
_INDIRECT_DATA_RANGES = tuple(
  range(
    table.indirect_data(first).address, table.indirect_data(last).address + 1
  )
  for first, last in ((1, 28), (29, 56))
)


def _item_map() -> list[table.Item | None]:
  items = list(table.items().values())
  for n in range(1, table.INDIRECT_ENTRIES + 1):
    items += [table.indirect_address(n), table.indirect_data(n)]
  item_at: list[table.Item | None] = [None] * _SIZE
  for item in items:
    for address in range(item.address, item.address + item.size):
      if item_at[address] is not None:
        raise AssertionError(f'control table items overlap at {address}')
      item_at[address] = item
  return item_at


# The item each address belongs to (None: reserved).
_ITEM_AT = _item_map()

_GAIN_RANGE = (0, 16_383)
# Valid values of items (beyond them: Data Range error); docs/dynamixel.md
# section 2. Items that the limit registers bound are checked in
# `_check_value`.
_RANGES = {
  table.ID: (0, protocol.MAX_ID),
  table.BAUD_RATE: (min(table.BAUD_RATES), max(table.BAUD_RATES)),
  table.RETURN_DELAY_TIME: (0, 254),
  table.PROTOCOL_TYPE: (1, 2),
  table.HOMING_OFFSET: (-1_044_479, 1_044_479),
  table.MOVING_THRESHOLD: (0, 1_023),
  table.TEMPERATURE_LIMIT: (0, 100),
  table.PWM_LIMIT: (0, 885),
  table.VELOCITY_LIMIT: (0, 1_023),
  table.MAX_POSITION_LIMIT: (0, 4_095),
  table.MIN_POSITION_LIMIT: (0, 4_095),
  table.TORQUE_ENABLE: (0, 1),
  table.LED: (0, 1),
  table.STATUS_RETURN_LEVEL: (0, 2),
  table.VELOCITY_I_GAIN: _GAIN_RANGE,
  table.VELOCITY_P_GAIN: _GAIN_RANGE,
  table.POSITION_D_GAIN: _GAIN_RANGE,
  table.POSITION_I_GAIN: _GAIN_RANGE,
  table.POSITION_P_GAIN: _GAIN_RANGE,
  table.FEEDFORWARD_2ND_GAIN: _GAIN_RANGE,
  table.FEEDFORWARD_1ST_GAIN: _GAIN_RANGE,
  table.BUS_WATCHDOG: (0, 127),
  table.PROFILE_ACCELERATION: (0, 32_767),
  table.PROFILE_VELOCITY: (0, 32_767),
}
_RANGES.update(
  {item: (64, _SIZE - 1) for item in _INDIRECT.values()}  # Indirect Address.
)
# Goal items bounded by a limit register (beyond it: Data Limit error).
_GOAL_LIMITS = {
  table.GOAL_PWM: table.PWM_LIMIT,
  table.GOAL_CURRENT: table.CURRENT_LIMIT,
  table.GOAL_VELOCITY: table.VELOCITY_LIMIT,
}
_MULTI_TURN_GOAL_RANGE = 1_048_575
_MULTI_TURN_MODES = (
  table.EXTENDED_POSITION_MODE,
  table.CURRENT_BASED_POSITION_MODE,
)
# Read-only measurements that survive a reboot (the motor does not move).
_MEASUREMENTS = (
  table.PRESENT_PWM,
  table.PRESENT_CURRENT,
  table.PRESENT_VELOCITY,
  table.PRESENT_POSITION,
  table.VELOCITY_TRAJECTORY,
  table.POSITION_TRAJECTORY,
  table.PRESENT_INPUT_VOLTAGE,
  table.PRESENT_TEMPERATURE,
)
_RAM_START = table.TORQUE_ENABLE.address
_REALTIME_TICK_PERIOD = 32_768  # ms.
_TICK_SLICE = slice(
  table.REALTIME_TICK.address,
  table.REALTIME_TICK.address + table.REALTIME_TICK.size,
)


@dataclasses.dataclass(frozen=True)
class _ModelDefaults:
  current_limit: int  # Also the largest Current Limit allowed.
  velocity_limit: int
  max_voltage_limit: int
  min_voltage_limit: int
  input_voltage: int  # Present Input Voltage of the virtual supply.


# docs/dynamixel.md section 2; values it lists as unknown are copied from the
# closest model (XH430-W350 from W210, XH430-V210 from V350).
_W_SERIES = dict(max_voltage_limit=160, min_voltage_limit=95, input_voltage=120)
_V_SERIES = dict(
  max_voltage_limit=300, min_voltage_limit=110, input_voltage=240
)
_MODEL_DEFAULTS = {
  1000: _ModelDefaults(648, 360, **_W_SERIES),
  1010: _ModelDefaults(648, 360, **_W_SERIES),
  1020: _ModelDefaults(1_193, 350, **_W_SERIES),
  1030: _ModelDefaults(1_193, 330, **_W_SERIES),
  1040: _ModelDefaults(689, 285, **_V_SERIES),
  1050: _ModelDefaults(689, 285, **_V_SERIES),
}
DEFAULT_MODEL_NUMBER = 1040  # XH430-V350, as on ROBEL's robots.
DEFAULT_FIRMWARE = 46
DEFAULT_TEMPERATURE = 35  # deg C.
_CENTER_TICKS = 2_048


def _encode(item: table.Item, value: int) -> bytes:
  low, high = _representable(item)
  value = int(value)
  if not low <= value <= high:
    raise ValueError(
      f'{value} does not fit the {item.size}-byte item at {item.address}'
    )
  return table.to_unsigned(value, item.size).to_bytes(item.size, 'little')


def _decode(raw: bytes | bytearray, item: table.Item) -> int:
  value = int.from_bytes(raw, 'little')
  return table.to_signed(value, item.size) if item.signed else value


def _representable(item: table.Item) -> tuple[int, int]:
  bits = 8 * item.size
  if item.signed:
    return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
  return 0, (1 << bits) - 1


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
    self._defaults = _MODEL_DEFAULTS.get(model_number, _MODEL_DEFAULTS[1030])
    self.lock = threading.RLock()
    self.table = self._initial_table(motor_id, factory=False)
    self.counters: collections.Counter[int] = collections.Counter()
    self.crc_errors = 0
    self._registered: tuple[int, bytes] | None = None

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
    for data_address, address_item in _INDIRECT.items():
      values[address_item] = data_address  # Each points at its own data.
    buffer = bytearray(_SIZE)
    for item, value in values.items():
      buffer[item.address : item.address + item.size] = _encode(item, value)
    return buffer

  # --- Registers -------------------------------------------------------------

  def get(self, item: table.Item) -> int:
    """The value of `item` (signed items as signed)."""
    with self.lock:
      return _decode(self.table[item.address : item.address + item.size], item)

  def set(self, item: table.Item, value: int) -> None:
    """Stores `value` in `item` without any firmware check.

    For drivers and tests; packets go through `write`.

    Raises:
      ValueError: if the value does not fit the item's size.
      TypeError: for a non-integer value (e.g. a float).
    """
    raw = _encode(item, operator.index(value))
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
      self.set(table.PRESENT_POSITION, position_ticks)
      self.set(table.PRESENT_VELOCITY, velocity_units)
      self.set(table.PRESENT_CURRENT, current_units)
      self.set(table.POSITION_TRAJECTORY, position_ticks)
      self.set(table.VELOCITY_TRAJECTORY, velocity_units)
      moving = abs(velocity_units) > self.get(table.MOVING_THRESHOLD)
      self.set(table.MOVING, int(moving))

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
      if address < 0 or end > _SIZE:
        return Error.ACCESS, b''
      tick = int(time.monotonic() * 1000) % _REALTIME_TICK_PERIOD
      self.table[_TICK_SLICE] = tick.to_bytes(2, 'little')
      data = self.table[address:end]
      for data_address in self._indirect_data_in(address, end):
        target = self.get(_INDIRECT[data_address])
        data[data_address - address] = (
          self.table[target] if target < _SIZE else 0
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
    keep = list(_MEASUREMENTS)
    if not factory:
      keep += _INDIRECT.values()
    saved = [(item, self.get(item)) for item in keep]
    start = 0 if factory else _RAM_START
    self.table[start:] = fresh[start:]
    for item, value in saved:
      self.set(item, value)
    self.set(table.GOAL_POSITION, self.present_position)
    self._registered = None

  @staticmethod
  def _indirect_data_in(start: int, end: int) -> list[int]:
    addresses = []
    for span in _INDIRECT_DATA_RANGES:
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
    if address < 0 or end > _SIZE:
      return Error.ACCESS, []
    torque_on = self.torque_enabled
    stores = []
    position = address
    while position < end:
      item = _ITEM_AT[position]
      if item is None:
        return Error.ACCESS, []
      if item.address != position or item.address + item.size > end:
        return Error.DATA_LENGTH, []
      raw = data[position - address : position - address + item.size]
      if position in _INDIRECT:
        target = self.get(_INDIRECT[position])
        target_item = _ITEM_AT[target] if target < _SIZE else None
        if target != position and (
          target_item is None or not target_item.writable or target in _INDIRECT
        ):
          return Error.ACCESS, []
        stores.append((target, raw))
      else:
        if not item.writable or (item.eeprom and torque_on):
          return Error.ACCESS, []
        result = self._check_value(item, _decode(raw, item))
        if result:
          return result, []
        stores.append((position, raw))
      position += item.size
    return Error.NONE, stores

  def _check_value(self, item: table.Item, value: int) -> int:
    bounds = _RANGES.get(item)
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
      elif mode in _MULTI_TURN_MODES and abs(value) > _MULTI_TURN_GOAL_RANGE:
        return Error.DATA_RANGE
    limit = _GOAL_LIMITS.get(item)
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


class Driver(Protocol):
  """Moves the motors: the bus calls it with its lock held.

  `servos` maps every servo's current ID to the servo; `ids` are the IDs
  concerned. A driver reads goals and torque from the servos and sets their
  present state (`VirtualServo.set_present`); it must not block for long.
  """

  def on_write(
    self, servos: Mapping[int, VirtualServo], ids: Sequence[int]
  ) -> None:
    """Called after an instruction changed these servos.

    That is a successful Write, Sync/Bulk Write or Action, a Reboot, Factory
    Reset or Clear; a write refused with an error does not count.
    """

  def on_read(
    self, servos: Mapping[int, VirtualServo], ids: Sequence[int]
  ) -> None:
    """Called before a read or sync/bulk read of these servos is answered."""


class IdealDriver:
  """Perfect servos: with torque on, a motor is at its goal at once.

  With torque on the present position equals the Goal Position, velocity and
  current are 0; with torque off the motor holds its position. The operating
  mode is ignored.
  """

  def on_write(
    self, servos: Mapping[int, VirtualServo], ids: Sequence[int]
  ) -> None:
    for motor_id in ids:
      servo = servos[motor_id]
      if servo.torque_enabled:
        servo.set_present(servo.goal_position, 0, 0)

  def on_read(
    self, servos: Mapping[int, VirtualServo], ids: Sequence[int]
  ) -> None:
    del servos, ids  # The state only changes on writes.


class Faults:
  """Communication faults, changeable at runtime from any thread.

  Mutate the attributes through the methods (or while holding `lock`).

  Attributes:
    absent: IDs that never answer (as if unplugged).
    mute: ID -> how many of the next packets addressed to that servo it
      ignores (neither executed nor answered: a timeout).
    corrupt_crc: ID -> how many of its next status packets carry a wrong CRC
      (for a fast read: its block's CRC).
    chain_break: in a sync/bulk read, servos after a silent one stay silent
      too, as on a real bus (docs/dynamixel.md section 1.7).
    lock: guards the attributes.
  """

  def __init__(
    self,
    absent: Iterable[int] = (),
    mute: Mapping[int, int] | None = None,
    corrupt_crc: Mapping[int, int] | None = None,
    chain_break: bool = True,
  ):
    self.lock = threading.Lock()
    self.absent = set(absent)
    self.mute = dict(mute or {})
    self.corrupt_crc = dict(corrupt_crc or {})
    self.chain_break = chain_break

  def set_absent(self, motor_id: int, absent: bool = True) -> None:
    with self.lock:
      if absent:
        self.absent.add(motor_id)
      else:
        self.absent.discard(motor_id)

  def mute_next(self, motor_id: int, count: int = 1) -> None:
    """Makes the servo ignore its next `count` packets."""
    with self.lock:
      self.mute[motor_id] = self.mute.get(motor_id, 0) + count

  def corrupt_next(self, motor_id: int, count: int = 1) -> None:
    """Breaks the CRC of the servo's next `count` status packets."""
    with self.lock:
      self.corrupt_crc[motor_id] = self.corrupt_crc.get(motor_id, 0) + count

  def clear(self) -> None:
    """Removes every fault (chain_break stays)."""
    with self.lock:
      self.absent.clear()
      self.mute.clear()
      self.corrupt_crc.clear()

  def is_absent(self, motor_id: int) -> bool:
    if not self.absent:  # Fast path, safe under the GIL.
      return False
    with self.lock:
      return motor_id in self.absent

  def take_mute(self, motor_id: int) -> bool:
    """Whether the servo ignores this packet (uses up one count)."""
    return self._take(self.mute, motor_id)

  def take_corrupt(self, motor_id: int) -> bool:
    """Whether this status packet gets a wrong CRC (uses up one count)."""
    return self._take(self.corrupt_crc, motor_id)

  def _take(self, counts: dict[int, int], motor_id: int) -> bool:
    if not counts:  # Fast path, safe under the GIL.
      return False
    with self.lock:
      count = counts.get(motor_id, 0)
      if count <= 0:
        return False
      if count == 1:
        del counts[motor_id]
      else:
        counts[motor_id] = count - 1
      return True


_READS = frozenset(
  {
    Instruction.READ,
    Instruction.SYNC_READ,
    Instruction.FAST_SYNC_READ,
    Instruction.BULK_READ,
    Instruction.FAST_BULK_READ,
  }
)


@dataclasses.dataclass
class _Reply:
  servo: VirtualServo
  reply_id: int
  error: int
  data: bytes = b''


class Bus:
  """Servos sharing one bus: executes instruction packets.

  Transport-free: `handle` takes a parsed packet and returns the bytes the
  servos send back. `PtyBusServer` puts it on a pseudo-terminal.

  Attributes:
    lock: held while a packet is handled (and by the servos' helpers).
    driver: moves the motors.
    faults: the communication faults to inject.
    stats: Counter of 'packets', 'crc_errors' and 'replies' (status
      packets sent).
  """

  def __init__(
    self,
    servos: Iterable[VirtualServo],
    driver: Driver | None = None,
    faults: Faults | None = None,
  ):
    """Initializes the bus.

    Args:
      servos: the servos on the bus (IDs must differ).
      driver: moves the motors; an `IdealDriver` by default.
      faults: communication faults; none by default.

    Raises:
      ValueError: if two servos have the same ID.
    """
    self.lock = threading.RLock()
    self._servos = tuple(servos)
    ids = [servo.motor_id for servo in self._servos]
    if len(set(ids)) != len(ids):
      raise ValueError(f'servo IDs must differ: {ids}')
    for servo in self._servos:
      servo.lock = self.lock
    self.driver: Driver = driver if driver is not None else IdealDriver()
    self.faults = faults if faults is not None else Faults()
    self.stats: collections.Counter[str] = collections.Counter()

  @property
  def servos(self) -> tuple[VirtualServo, ...]:
    return self._servos

  def by_id(self) -> dict[int, VirtualServo]:
    """Servos by their current ID (the register: writes may change it)."""
    with self.lock:
      servos = {}
      for servo in self._servos:
        servos.setdefault(servo.motor_id, servo)
      return servos

  def servo(self, motor_id: int) -> VirtualServo:
    """The servo with this ID.

    Raises:
      KeyError: if there is none.
    """
    servo = self.by_id().get(motor_id)
    if servo is None:
      raise KeyError(f'no servo with ID {motor_id}')
    return servo

  __getitem__ = servo

  def goal_positions(self) -> dict[int, int]:
    """The last accepted Goal Position of every servo, ticks."""
    with self.lock:
      return {i: s.goal_position for i, s in self.by_id().items()}

  def handle(
    self, packet: protocol.Packet, baud_rate: int | None = None
  ) -> bytes:
    """Executes one packet.

    Args:
      packet: a parsed packet (status packets are ignored).
      baud_rate: the sender's bit rate; servos set to another rate do not
        hear the packet. None: everyone hears it.

    Returns:
      The status packets sent back, concatenated (possibly empty).
    """
    with self.lock:
      self.stats['packets'] += 1
      if packet.is_status:
        return b''
      if not packet.crc_ok:
        self.stats['crc_errors'] += 1
        replies = self._crc_error(packet, baud_rate)
      else:
        handler = self._HANDLERS.get(packet.instruction, Bus._unknown)
        replies = handler(self, packet, baud_rate)
      if isinstance(replies, bytes):
        return replies
      return b''.join(self._encode(reply) for reply in replies)

  # --- Helpers ---------------------------------------------------------------

  def _addressed(self, packet_id: int) -> list[VirtualServo]:
    if packet_id == protocol.BROADCAST_ID:
      return sorted(self._servos, key=lambda servo: servo.motor_id)
    return [s for s in self._servos if s.motor_id == packet_id]

  def _listen(
    self,
    servo: VirtualServo,
    baud_rate: int | None,
    instruction: int | None,
  ) -> bool:
    """Whether the servo receives the packet (counts it if so)."""
    motor_id = servo.motor_id
    if self.faults.is_absent(motor_id):
      return False
    if baud_rate is not None and servo.baud_rate != baud_rate:
      return False
    if self.faults.take_mute(motor_id):
      return False
    if instruction is not None:
      servo.counters[instruction] += 1
    return True

  @staticmethod
  def _answers(servo: VirtualServo, instruction: int) -> bool:
    if instruction == Instruction.PING:
      return True
    level = servo.status_return_level
    return level >= 1 if instruction in _READS else level >= 2

  def _encode(self, reply: _Reply) -> bytes:
    packet = protocol.encode_status(reply.reply_id, reply.error, reply.data)
    if self.faults.take_corrupt(reply.servo.motor_id):
      packet = packet[:-2] + bytes([packet[-2] ^ 0xFF, packet[-1]])
    self.stats['replies'] += 1
    return packet

  def _wrote(self, ids: list[int]) -> None:
    if ids:
      self.driver.on_write(self.by_id(), ids)

  def _simple(
    self,
    packet: protocol.Packet,
    baud_rate: int | None,
    execute: Callable[[VirtualServo], int],
    touches: bool = True,
  ) -> list[_Reply]:
    """Runs a unicast/broadcast instruction answered by an empty status."""
    broadcast = packet.id == protocol.BROADCAST_ID
    replies, touched = [], []
    for servo in self._addressed(packet.id):
      if not self._listen(servo, baud_rate, packet.instruction):
        continue
      answers = not broadcast and self._answers(servo, packet.instruction)
      # The alert bit as the instruction arrives (e.g. before a reboot).
      alert = servo.status_error(Error.NONE)
      result = execute(servo)
      if result == Error.NONE and touches:
        touched.append(servo.motor_id)
      if answers:
        replies.append(_Reply(servo, packet.id, alert | result))
    self._wrote(touched)
    return replies

  def _malformed(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    """Unicast: Instruction error; broadcast: ignored."""
    return self._simple(packet, baud_rate, lambda _: Error.INSTRUCTION, False)

  # --- Instructions ----------------------------------------------------------

  def _crc_error(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    if packet.id == protocol.BROADCAST_ID:
      return []
    replies = []
    for servo in self._addressed(packet.id):
      if self._listen(servo, baud_rate, None):
        servo.crc_errors += 1
        if self._answers(servo, packet.instruction):
          error = servo.status_error(Error.CRC)
          replies.append(_Reply(servo, packet.id, error))
    return replies

  def _unknown(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    return self._malformed(packet, baud_rate)

  def _ping(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    replies = []
    for servo in self._addressed(packet.id):
      if self._listen(servo, baud_rate, Instruction.PING):
        data = servo.model_number.to_bytes(2, 'little')
        data += bytes([servo.firmware])
        error = servo.status_error(Error.NONE)
        replies.append(_Reply(servo, servo.motor_id, error, data))
    return replies

  def _read(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    if packet.id == protocol.BROADCAST_ID:  # Executed by nobody, unanswered.
      for servo in self._servos:
        self._listen(servo, baud_rate, Instruction.READ)
      return []
    if len(packet.params) != 4:
      return self._malformed(packet, baud_rate)
    address = int.from_bytes(packet.params[:2], 'little')
    length = int.from_bytes(packet.params[2:], 'little')
    replies = []
    for servo in self._addressed(packet.id):
      if not self._listen(servo, baud_rate, Instruction.READ):
        continue
      self.driver.on_read(self.by_id(), [servo.motor_id])
      result, data = servo.read(address, length)
      if self._answers(servo, Instruction.READ):
        error = servo.status_error(result)
        replies.append(_Reply(servo, packet.id, error, data))
    return replies

  def _write(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    if len(packet.params) < 3:
      return self._malformed(packet, baud_rate)
    address = int.from_bytes(packet.params[:2], 'little')
    data = packet.params[2:]
    if packet.instruction == Instruction.REG_WRITE:
      return self._simple(
        packet, baud_rate, lambda s: s.reg_write(address, data), False
      )
    return self._simple(packet, baud_rate, lambda s: s.write(address, data))

  def _action(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    return self._simple(packet, baud_rate, VirtualServo.action)

  def _reboot(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    def reboot(servo: VirtualServo) -> int:
      servo.reboot()
      return Error.NONE

    return self._simple(packet, baud_rate, reboot)

  def _factory_reset(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    if len(packet.params) != 1:
      return self._malformed(packet, baud_rate)
    option = packet.params[0]
    if packet.id == protocol.BROADCAST_ID and option == protocol.RESET_ALL:
      return self._simple(packet, baud_rate, lambda _: Error.NONE, False)
    return self._simple(packet, baud_rate, lambda s: s.factory_reset(option))

  def _clear(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    if packet.params != protocol.CLEAR_MULTI_TURN:
      return self._malformed(packet, baud_rate)
    return self._simple(packet, baud_rate, VirtualServo.clear_multi_turn)

  def _sync_read(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply] | bytes:
    params = packet.params
    if packet.id != protocol.BROADCAST_ID or len(params) < 5:
      return []
    address = int.from_bytes(params[:2], 'little')
    length = int.from_bytes(params[2:4], 'little')
    requests = [(i, address, length) for i in dict.fromkeys(params[4:])]
    return self._group_read(packet.instruction, requests, baud_rate)

  def _bulk_read(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply] | bytes:
    params = packet.params
    if packet.id != protocol.BROADCAST_ID or not params or len(params) % 5:
      return []
    requests = {}
    for start in range(0, len(params), 5):
      entry = params[start : start + 5]
      address = int.from_bytes(entry[1:3], 'little')
      requests.setdefault(
        entry[0], (entry[0], address, int.from_bytes(entry[3:], 'little'))
      )
    return self._group_read(
      packet.instruction, list(requests.values()), baud_rate
    )

  def _group_read(
    self,
    instruction: int,
    requests: list[tuple[int, int, int]],
    baud_rate: int | None,
  ) -> list[_Reply] | bytes:
    """Sync/bulk reads: the servos answer in request order."""
    servos = self.by_id()
    listening = {}
    for motor_id, _, _ in requests:
      servo = servos.get(motor_id)
      if servo is not None and self._listen(servo, baud_rate, instruction):
        listening[motor_id] = servo
    if listening:
      self.driver.on_read(servos, list(listening))
    replies = []
    for motor_id, address, length in requests:
      servo = listening.get(motor_id)
      if servo is None or not self._answers(servo, instruction):
        if self.faults.chain_break:
          break  # The next servo waits for a packet that never comes.
        continue
      result, data = servo.read(address, length)
      replies.append(_Reply(servo, motor_id, servo.status_error(result), data))
    fast = instruction in (
      Instruction.FAST_SYNC_READ,
      Instruction.FAST_BULK_READ,
    )
    if not fast:
      return replies
    if not replies:
      return b''
    encoder = protocol.FastStatusEncoder([length for _, _, length in requests])
    lengths = {motor_id: length for motor_id, _, length in requests}
    for reply in replies:
      data = reply.data.ljust(lengths[reply.reply_id], b'\0')
      corrupt = self.faults.take_corrupt(reply.reply_id)
      encoder.add(reply.error, reply.reply_id, data, corrupt)
    self.stats['replies'] += 1
    return encoder.to_bytes()

  def _sync_write(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    params = packet.params
    if packet.id != protocol.BROADCAST_ID or len(params) < 4:
      return []
    address = int.from_bytes(params[:2], 'little')
    length = int.from_bytes(params[2:4], 'little')
    body = params[4:]
    if length == 0 or not body or len(body) % (length + 1):
      return []
    writes = [
      (body[i], address, body[i + 1 : i + 1 + length])
      for i in range(0, len(body), length + 1)
    ]
    return self._group_write(packet.instruction, writes, baud_rate)

  def _bulk_write(
    self, packet: protocol.Packet, baud_rate: int | None
  ) -> list[_Reply]:
    params = packet.params
    if packet.id != protocol.BROADCAST_ID:
      return []
    writes, position = [], 0
    while position < len(params):
      if position + 5 > len(params):
        return []
      motor_id = params[position]
      address = int.from_bytes(params[position + 1 : position + 3], 'little')
      length = int.from_bytes(params[position + 3 : position + 5], 'little')
      data = params[position + 5 : position + 5 + length]
      if length == 0 or len(data) != length:
        return []
      writes.append((motor_id, address, data))
      position += 5 + length
    return self._group_write(packet.instruction, writes, baud_rate)

  def _group_write(
    self,
    instruction: int,
    writes: list[tuple[int, int, bytes]],
    baud_rate: int | None,
  ) -> list[_Reply]:
    servos = self.by_id()
    touched, seen = [], set()
    for motor_id, address, data in writes:
      servo = servos.get(motor_id)
      if servo is None or motor_id in seen:  # An ID may appear only once.
        continue
      seen.add(motor_id)
      listens = self._listen(servo, baud_rate, instruction)
      if listens and servo.write(address, data) == Error.NONE:
        touched.append(motor_id)
    self._wrote(touched)
    return []

  _HANDLERS = {
    Instruction.PING: _ping,
    Instruction.READ: _read,
    Instruction.WRITE: _write,
    Instruction.REG_WRITE: _write,
    Instruction.ACTION: _action,
    Instruction.FACTORY_RESET: _factory_reset,
    Instruction.REBOOT: _reboot,
    Instruction.CLEAR: _clear,
    Instruction.SYNC_READ: _sync_read,
    Instruction.FAST_SYNC_READ: _sync_read,
    Instruction.BULK_READ: _bulk_read,
    Instruction.FAST_BULK_READ: _bulk_read,
    Instruction.SYNC_WRITE: _sync_write,
    Instruction.BULK_WRITE: _bulk_write,
  }


# termios speed constants -> bits per second, for the rates servos support.
_TERMIOS_SPEEDS = {
  getattr(termios, f'B{rate}'): rate
  for rate in table.BAUD_RATES.values()
  if hasattr(termios, f'B{rate}')
}
_READ_SIZE = 4096
_SEND_TIMEOUT_S = 0.1
_EIO_BACKOFF_S = 0.01


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
  they are dropped after 0.1 s. Exceptions raised while handling a packet
  are logged and collected in `errors`, and the server carries on (an
  error of the pty itself ends the thread, also recorded in `errors`).

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
      self.stats['bytes_in'] += received

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


# --- Command line ------------------------------------------------------------

# --driver values: factories of a driver for a robot configuration.
DriverFactory = Callable[[config.RobotConfig], Driver]
# The scene a standalone simulated robot runs: one with every motor's joint
# (the D'Claw's includes the valve that motor 50 reads).
_SIMULATED_SCENES = {'dclaw': 'turn_fixed', 'dkitty': 'stand_fixed'}


def _simulated_robot(robot_config: config.RobotConfig) -> Driver:
  # Imported here: they need MuJoCo, and the command line builds the scene.
  from robel_dm import suite  # noqa: PLC0415
  from robel_dm.hardware import sim_robot  # noqa: PLC0415

  scene = suite.load(
    robot_config.robot,
    _SIMULATED_SCENES[robot_config.robot],
    seed=0,
    time_limit=math.inf,
  )
  return sim_robot.SimulatedRobot(scene, robot_config, realtime=True)


DRIVERS: dict[str, DriverFactory] = {
  'ideal': lambda robot_config: IdealDriver(),
  # A MuJoCo simulation of the robot, advancing with the wall clock.
  'sim': _simulated_robot,
}


def robot_motor_ids(robot_config: config.RobotConfig) -> list[int]:
  """Every motor of a robot: joints, then auxiliary motors."""
  return [motor.id for motor in robot_config.joints + robot_config.auxiliary]


def build_bus(
  robot_config: config.RobotConfig,
  driver: str = 'ideal',
  model_number: int = DEFAULT_MODEL_NUMBER,
) -> Bus:
  """A bus with one servo per motor of `robot_config`.

  Args:
    robot_config: the robot.
    driver: a key of DRIVERS.
    model_number: the servos' model.

  Raises:
    ValueError: for an unknown driver.
  """
  if driver not in DRIVERS:
    raise ValueError(f'unknown driver {driver!r}; known: {sorted(DRIVERS)}')
  servos = make_servos(robot_motor_ids(robot_config), model_number)
  return Bus(servos, driver=DRIVERS[driver](robot_config))


def _define_flags():
  from absl import flags  # Command line only.

  return {
    'robot': flags.DEFINE_string(
      'robot', 'dclaw', 'Robot whose shipped configuration to serve.'
    ),
    'config': flags.DEFINE_string(
      'config', None, 'Robot configuration file (JSON); overrides --robot.'
    ),
    'driver': flags.DEFINE_enum(
      'driver',
      'sim',
      sorted(DRIVERS),
      'What moves the motors: sim (a MuJoCo simulation of the robot, in real '
      'time) or ideal (every motor at its goal at once).',
    ),
    'model_number': flags.DEFINE_integer(
      'model_number', DEFAULT_MODEL_NUMBER, 'Model number of every servo.'
    ),
  }


def _serve_until_signalled(flag_values) -> int:
  try:
    if flag_values['config'].value:
      robot_config = config.load(flag_values['config'].value)
    else:
      robot_config = config.default(flag_values['robot'].value)
  except config.ConfigError as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  bus = build_bus(
    robot_config,
    flag_values['driver'].value,
    flag_values['model_number'].value,
  )
  stop = threading.Event()
  for signal_number in (signal.SIGINT, signal.SIGTERM):
    signal.signal(signal_number, lambda *_: stop.set())
  with PtyBusServer(bus) as server:
    print(server.device_path, flush=True)
    logging.info(
      'serving %s motors %s on %s',
      robot_config.robot,
      robot_motor_ids(robot_config),
      server.device_path,
    )
    stop.wait()
  return 0


def main(argv: Sequence[str] | None = None) -> None:
  """Serves a robot's motors until SIGINT or SIGTERM."""
  from absl import app  # Command line only.

  flag_values = _define_flags()

  def run(args: Sequence[str]) -> int:
    if len(args) > 1:
      raise app.UsageError(f'unexpected arguments: {args[1:]}')
    return _serve_until_signalled(flag_values)

  app.run(run, argv=argv)


if __name__ == '__main__':
  main()
