"""A virtual chain of Dynamixel X-series servos on a pseudo-terminal.

The unmodified `dynamixel_sdk` (or any Protocol 2.0 client) opens
`PtyBusServer.device_path` as if it were `/dev/ttyUSB0` and exchanges real
packets with it (docs/dynamixel.md section 4):

  servos = make_servos([10, 11, 12])
  with PtyBusServer(Bus(servos)) as server:
    port = dynamixel_sdk.PortHandler(server.device_path)
    ...

Modules: `servo` (a servo's control table and firmware, on the rules in
`registers`), `bus` (packet dispatch and the drivers that move the motors),
`faults` (injected communication failures) and `transport` (the
pseudo-terminal). `robel-virtual-bus --robot=dclaw`
serves a robot's motors and prints the device path; `standalone_bus`
starts it for a program and stops it after.
"""

from robel_dm.hardware.virtual.bus import (
  Bus,
  Driver,
  IdealDriver,
  robot_motor_ids,
)
from robel_dm.hardware.virtual.faults import Faults
from robel_dm.hardware.virtual.servo import (
  DEFAULT_FIRMWARE,
  DEFAULT_MODEL_NUMBER,
  DEFAULT_TEMPERATURE,
  VirtualServo,
  make_servos,
)
from robel_dm.hardware.virtual.transport import PtyBusServer, standalone_bus

__all__ = [
  'DEFAULT_FIRMWARE',
  'DEFAULT_MODEL_NUMBER',
  'DEFAULT_TEMPERATURE',
  'Bus',
  'Driver',
  'Faults',
  'IdealDriver',
  'PtyBusServer',
  'VirtualServo',
  'make_servos',
  'robot_motor_ids',
  'standalone_bus',
]
