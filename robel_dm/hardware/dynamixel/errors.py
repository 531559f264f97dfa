"""The errors of the Dynamixel client, and how hardware errors read.

`client.DynamixelClient` raises them; `client` re-exports them, so callers
catch `client.DynamixelError` and its subclasses.
"""

from robel_dm.hardware.dynamixel import control_table as table


class DynamixelError(RuntimeError):
  """A communication or motor failure; `motor_ids` names the motors."""

  def __init__(self, message: str, motor_ids=()):
    super().__init__(message)
    self.motor_ids = tuple(motor_ids)


class MissingMotorError(DynamixelError):
  """Motors that do not answer."""


class RobotReleasedError(DynamixelError):
  """The robot was released after an error and must be reset first."""


class MotorFaultError(DynamixelError):
  """Motors that report a hardware error (overload, overheating, ...)."""

  def __init__(self, message: str, errors: dict[int, int]):
    super().__init__(message, errors)
    self.errors = dict(errors)


def describe_hardware_errors(errors: dict[int, int]) -> str:
  """'motor 21: overload (0x20); ...' for motor ID -> error bits."""
  return '; '.join(
    f'motor {motor_id}: {", ".join(table.hardware_error_names(bits))}'
    f' (0x{bits:02x})'
    for motor_id, bits in sorted(errors.items())
  )
