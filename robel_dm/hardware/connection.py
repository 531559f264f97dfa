"""What a hardware environment runs on, once its robot is opened."""

from __future__ import annotations

from collections.abc import Callable
import dataclasses
from typing import TYPE_CHECKING

if TYPE_CHECKING:
  from robel_dm.hardware import clock as clock_lib
  from robel_dm.hardware import config as config_lib
  from robel_dm.hardware import robot as robot_lib
  from robel_dm.hardware.tracking.tracker import TorsoTracker
  from robel_dm.hardware.virtual.bus import Bus
  from robel_dm.hardware.virtual.sim_robot import SimulatedRobot

# A free-floating robot's torso: (position, quaternion, linear velocity,
# angular velocity in the torso frame).
TorsoSource = Callable[[], tuple]


@dataclasses.dataclass
class Connection:
  """The opened robot a `HardwareEnvironment` and its physics run on.

  Attributes:
    robot: the motors.
    robot_config: their configuration.
    clock: paces the control loop (wall or simulated time).
    auxiliary_joints: auxiliary motor name -> the model joint it measures
      (None for the guide, which measures none).
    joint_limits: goal limits from the robot configuration (joint name ->
      (low, high); empty where it sets none).
    reset: the reset procedure (see `hardware.resets`).
    torso_source: a free-floating robot's torso pose, or None.
    tracker: the motion tracker, or None; recalibrated after every reset.
    guide: the guide motor's mode (`options.GUIDE_MODES`), or None.
    bus: the in-process virtual bus, or None.
    simulation: the simulation behind the virtual bus, or None.
    on_close: called when the environment closes.
  """

  robot: robot_lib.HardwareRobot
  robot_config: config_lib.RobotConfig
  clock: clock_lib.Clock
  auxiliary_joints: dict[str, object | None]
  joint_limits: dict[str, tuple[float, float]]
  reset: Callable[..., None]
  torso_source: TorsoSource | None = None
  tracker: TorsoTracker | None = None
  guide: str | None = None
  bus: Bus | None = None
  simulation: SimulatedRobot | None = None
  on_close: list[Callable[[], None]] = dataclasses.field(default_factory=list)
