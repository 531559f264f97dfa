"""Dynamixel X-series (Protocol 2.0) control table and units.

Addresses, sizes and units of the X430 servos ROBEL uses (docs/dynamixel.md
section 2); the single source of these numbers for the client, the virtual
bus and the diagnostics.
"""

import dataclasses
import math

PROTOCOL_VERSION = 2.0
DEFAULT_BAUD_RATE = 1_000_000


@dataclasses.dataclass(frozen=True)
class Item:
  """A control-table item: address, size in bytes, signedness, writability."""

  address: int
  size: int
  signed: bool = False
  writable: bool = True
  eeprom: bool = False


MODEL_NUMBER = Item(0, 2, writable=False, eeprom=True)
MODEL_INFORMATION = Item(2, 4, writable=False, eeprom=True)
FIRMWARE_VERSION = Item(6, 1, writable=False, eeprom=True)
ID = Item(7, 1, eeprom=True)
BAUD_RATE = Item(8, 1, eeprom=True)
RETURN_DELAY_TIME = Item(9, 1, eeprom=True)
DRIVE_MODE = Item(10, 1, eeprom=True)
OPERATING_MODE = Item(11, 1, eeprom=True)
SECONDARY_ID = Item(12, 1, eeprom=True)
PROTOCOL_TYPE = Item(13, 1, eeprom=True)
HOMING_OFFSET = Item(20, 4, signed=True, eeprom=True)
MOVING_THRESHOLD = Item(24, 4, eeprom=True)
TEMPERATURE_LIMIT = Item(31, 1, eeprom=True)
MAX_VOLTAGE_LIMIT = Item(32, 2, eeprom=True)
MIN_VOLTAGE_LIMIT = Item(34, 2, eeprom=True)
PWM_LIMIT = Item(36, 2, eeprom=True)
CURRENT_LIMIT = Item(38, 2, eeprom=True)
VELOCITY_LIMIT = Item(44, 4, eeprom=True)
MAX_POSITION_LIMIT = Item(48, 4, eeprom=True)
MIN_POSITION_LIMIT = Item(52, 4, eeprom=True)
STARTUP_CONFIGURATION = Item(60, 1, eeprom=True)
SHUTDOWN = Item(63, 1, eeprom=True)
TORQUE_ENABLE = Item(64, 1)
LED = Item(65, 1)
STATUS_RETURN_LEVEL = Item(68, 1)
REGISTERED_INSTRUCTION = Item(69, 1, writable=False)
HARDWARE_ERROR_STATUS = Item(70, 1, writable=False)
VELOCITY_I_GAIN = Item(76, 2)
VELOCITY_P_GAIN = Item(78, 2)
POSITION_D_GAIN = Item(80, 2)
POSITION_I_GAIN = Item(82, 2)
POSITION_P_GAIN = Item(84, 2)
FEEDFORWARD_2ND_GAIN = Item(88, 2)
FEEDFORWARD_1ST_GAIN = Item(90, 2)
BUS_WATCHDOG = Item(98, 1)
GOAL_PWM = Item(100, 2, signed=True)
GOAL_CURRENT = Item(102, 2, signed=True)
GOAL_VELOCITY = Item(104, 4, signed=True)
PROFILE_ACCELERATION = Item(108, 4)
PROFILE_VELOCITY = Item(112, 4)
GOAL_POSITION = Item(116, 4, signed=True)
REALTIME_TICK = Item(120, 2, writable=False)
MOVING = Item(122, 1, writable=False)
MOVING_STATUS = Item(123, 1, writable=False)
PRESENT_PWM = Item(124, 2, signed=True, writable=False)
PRESENT_CURRENT = Item(126, 2, signed=True, writable=False)
PRESENT_VELOCITY = Item(128, 4, signed=True, writable=False)
PRESENT_POSITION = Item(132, 4, signed=True, writable=False)
VELOCITY_TRAJECTORY = Item(136, 4, signed=True, writable=False)
POSITION_TRAJECTORY = Item(140, 4, signed=True, writable=False)
PRESENT_INPUT_VOLTAGE = Item(144, 2, writable=False)
PRESENT_TEMPERATURE = Item(146, 1, writable=False)

# Indirect addressing: Indirect Address n (2 bytes) holds the address (64..661)
# that Indirect Data n (1 byte) reads and writes. Entries 1-28 and 29-56 sit
# in two blocks.
INDIRECT_ENTRIES = 56
_INDIRECT_BLOCK = 28
_INDIRECT_ADDRESS_STARTS = (168, 578)
_INDIRECT_DATA_STARTS = (224, 634)
INDIRECT_TARGETS = range(64, 662)

# Addresses 0..661 (the last Indirect Data).
CONTROL_TABLE_SIZE = 662

# One sync read covers goal position through present position (116..135):
# the goal read back confirms the last goal write, then current, velocity
# and position.
STATE_BLOCK_ADDRESS = GOAL_POSITION.address
STATE_BLOCK_SIZE = PRESENT_POSITION.address + 4 - GOAL_POSITION.address

# Operating modes (address 11).
OPERATING_MODES = {
  0: 'current',
  1: 'velocity',
  3: 'position',
  4: 'extended position',
  5: 'current-based position',
  16: 'PWM',
}
POSITION_MODE = 3
EXTENDED_POSITION_MODE = 4
CURRENT_BASED_POSITION_MODE = 5

# Baud-rate register values (address 8) -> bits per second.
BAUD_RATES = {
  0: 9_600,
  1: 57_600,
  2: 115_200,
  3: 1_000_000,
  4: 2_000_000,
  5: 3_000_000,
  6: 4_000_000,
  7: 4_500_000,
}

# Hardware Error Status (address 70) bits.
HARDWARE_ERRORS = {
  0x01: 'input voltage out of range',
  0x04: 'overheating',
  0x08: 'motor encoder',
  0x10: 'electrical shock or insufficient power',
  0x20: 'overload',
}
# The alert bit of a status packet's error byte: a hardware error is latched.
ALERT_BIT = 0x80

# Units.
RADIANS_PER_TICK = 2 * math.pi / 4096
RADIANS_PER_SECOND_PER_UNIT = 0.229 * 2 * math.pi / 60  # 0.229 rpm.
VOLTS_PER_UNIT = 0.1
# Joint torque per ampere of motor current, N m/A: an X430 stalls at about
# 4.8 N m and 2.2 A. The virtual bus reports currents with it, and system
# identification predicts them with it (real servos are only roughly linear).
TORQUE_PER_AMPERE = 2.2

# Model number -> (name, current unit in mA). W-series 2.69 mA, V-series
# 1.34 mA (docs/dynamixel.md section 2).
MODELS = {
  1000: ('XH430-W350', 2.69),
  1010: ('XH430-W210', 2.69),
  1020: ('XM430-W350', 2.69),
  1030: ('XM430-W210', 2.69),
  1040: ('XH430-V350', 1.34),
  1050: ('XH430-V210', 1.34),
}


def indirect_address(n: int) -> Item:
  """Indirect Address `n` (1..56)."""
  block, offset = divmod(_indirect_index(n), _INDIRECT_BLOCK)
  return Item(_INDIRECT_ADDRESS_STARTS[block] + 2 * offset, 2)


def indirect_data(n: int) -> Item:
  """Indirect Data `n` (1..56)."""
  block, offset = divmod(_indirect_index(n), _INDIRECT_BLOCK)
  return Item(_INDIRECT_DATA_STARTS[block] + offset, 1)


def _indirect_index(n: int) -> int:
  if not 1 <= n <= INDIRECT_ENTRIES:
    raise ValueError(f'indirect entries are 1..{INDIRECT_ENTRIES}, got {n}')
  return n - 1


def items() -> dict[str, Item]:
  """Every named item above (not the indirect entries), by name."""
  return {
    name: value for name, value in globals().items() if isinstance(value, Item)
  }


def hardware_error_names(bits: int) -> list[str]:
  """Names of the set bits of a Hardware Error Status value."""
  return [name for bit, name in HARDWARE_ERRORS.items() if bits & bit]


def to_signed(value: int, size: int) -> int:
  """Two's-complement interpretation of an unsigned `size`-byte value."""
  bits = 8 * size
  return value - (1 << bits) if value & (1 << (bits - 1)) else value


def to_unsigned(value: int, size: int) -> int:
  """The unsigned `size`-byte encoding of a signed integer."""
  return value & ((1 << (8 * size)) - 1)
