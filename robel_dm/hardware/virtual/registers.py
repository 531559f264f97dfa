"""The X430 control table as the firmware keeps it, for `VirtualServo`.

Where each item lies (and which addresses are reserved), the values each
writable item accepts, the limit registers that bound goals, what a reboot
keeps, and each model's factory limits (docs/dynamixel.md section 2).
`servo.VirtualServo` applies these rules to the packets it receives.
"""

import dataclasses

from robel_dm.hardware.dynamixel import control_table as table
from robel_dm.hardware.dynamixel import protocol

SIZE = table.CONTROL_TABLE_SIZE

# Indirect Data address -> the Indirect Address item that redirects it.
INDIRECT = {
  table.indirect_data(n).address: table.indirect_address(n)
  for n in range(1, table.INDIRECT_ENTRIES + 1)
}
INDIRECT_DATA_RANGES = tuple(
  range(
    table.indirect_data(first).address, table.indirect_data(last).address + 1
  )
  for first, last in ((1, 28), (29, 56))
)


def _item_map() -> list[table.Item | None]:
  items = list(table.items().values())
  for n in range(1, table.INDIRECT_ENTRIES + 1):
    items += [table.indirect_address(n), table.indirect_data(n)]
  item_at: list[table.Item | None] = [None] * SIZE
  for item in items:
    for address in range(item.address, item.address + item.size):
      if item_at[address] is not None:
        raise AssertionError(f'control table items overlap at {address}')
      item_at[address] = item
  return item_at


# The item each address belongs to (None: reserved).
ITEM_AT = _item_map()

_GAIN_RANGE = (0, 16_383)
# Valid values of items (beyond them: Data Range error); docs/dynamixel.md
# section 2. Items that the limit registers bound are checked in
# `servo.VirtualServo._check_value`.
RANGES = {
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
RANGES.update(
  {item: (64, SIZE - 1) for item in INDIRECT.values()}  # Indirect Address.
)
# Goal items bounded by a limit register (beyond it: Data Limit error).
GOAL_LIMITS = {
  table.GOAL_PWM: table.PWM_LIMIT,
  table.GOAL_CURRENT: table.CURRENT_LIMIT,
  table.GOAL_VELOCITY: table.VELOCITY_LIMIT,
}
MULTI_TURN_GOAL_RANGE = 1_048_575
MULTI_TURN_MODES = (
  table.EXTENDED_POSITION_MODE,
  table.CURRENT_BASED_POSITION_MODE,
)
# Read-only measurements that survive a reboot (the motor does not move).
MEASUREMENTS = (
  table.PRESENT_PWM,
  table.PRESENT_CURRENT,
  table.PRESENT_VELOCITY,
  table.PRESENT_POSITION,
  table.VELOCITY_TRAJECTORY,
  table.POSITION_TRAJECTORY,
  table.PRESENT_INPUT_VOLTAGE,
  table.PRESENT_TEMPERATURE,
)
RAM_START = table.TORQUE_ENABLE.address
REALTIME_TICK_PERIOD = 32_768  # ms.
TICK_SLICE = slice(
  table.REALTIME_TICK.address,
  table.REALTIME_TICK.address + table.REALTIME_TICK.size,
)


@dataclasses.dataclass(frozen=True)
class ModelDefaults:
  """Factory values that differ between models."""

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
MODEL_DEFAULTS = {
  1000: ModelDefaults(648, 360, **_W_SERIES),
  1010: ModelDefaults(648, 360, **_W_SERIES),
  1020: ModelDefaults(1_193, 350, **_W_SERIES),
  1030: ModelDefaults(1_193, 330, **_W_SERIES),
  1040: ModelDefaults(689, 285, **_V_SERIES),
  1050: ModelDefaults(689, 285, **_V_SERIES),
}


def encode(item: table.Item, value: int) -> bytes:
  """`value` as the item's little-endian bytes.

  Raises:
    ValueError: if the value does not fit the item's size.
  """
  low, high = _representable(item)
  value = int(value)
  if not low <= value <= high:
    raise ValueError(
      f'{value} does not fit the {item.size}-byte item at {item.address}'
    )
  return table.to_unsigned(value, item.size).to_bytes(item.size, 'little')


def decode(raw: bytes | bytearray, item: table.Item) -> int:
  """The item's value in `raw` (signed items as signed)."""
  value = int.from_bytes(raw, 'little')
  return table.to_signed(value, item.size) if item.signed else value


def _representable(item: table.Item) -> tuple[int, int]:
  bits = 8 * item.size
  if item.signed:
    return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
  return 0, (1 << bits) - 1
