"""The D'Claw: a 9-DoF three-finger hand of Dynamixel XH430 servos."""

from dm_control import composer, mjcf
from dm_control.composer.observation import observable
import numpy as np

from robel_dm.entities import limits, servo_robot

# Joints in action order; motor IDs are the digits (docs/robel_reference.md
# sections 3.2, 4.1).
JOINT_NAMES = (
  'FFJ10', 'FFJ11', 'FFJ12',
  'MFJ20', 'MFJ21', 'MFJ22',
  'THJ30', 'THJ31', 'THJ32',
)  # fmt: skip
FINGERTIP_SITE_NAMES = ('FFtip', 'MFtip', 'THtip')

# ROBEL's per-joint velocity limit used by the action clamp, rad/s.
MAX_JOINT_SPEED = 2 * np.pi / 3

# The claw pose of Turn/Screw resets, also the "nominal" pose of their reward:
# (top, middle, bottom) per finger, rad.
RESET_POSE = np.tile([0.0, -np.pi / 3, np.pi / 3], 3)


# ROBEL's D'Claw safety thresholds (docs/robel_reference.md section 2.3).
SAFETY_LIMITS = limits.SafetyLimits(
  position_margin=np.deg2rad(5.0), max_speed=1.0, max_current=200.0
)


class DClaw(servo_robot.ServoRobot):
  """The D'Claw hand, hanging from its mount point (the model's origin)."""

  MODEL = ('dclaw', 'dclaw.xml')
  DEFAULT_NAME = 'dclaw'
  JOINT_NAMES = JOINT_NAMES
  MAX_JOINT_SPEED = MAX_JOINT_SPEED
  SAFETY_LIMITS = SAFETY_LIMITS

  def _find_parts(self, root: mjcf.RootElement) -> None:
    self._fingertip_sites = servo_robot.find_all(
      root, 'site', FINGERTIP_SITE_NAMES
    )

  def _build_observables(self) -> 'DClawObservables':
    return DClawObservables(self)

  @property
  def fingertip_sites(self) -> tuple[mjcf.Element, ...]:
    return self._fingertip_sites


class DClawObservables(servo_robot.JointObservables):
  """Joint and fingertip observables (disabled until a task enables them)."""

  @composer.observable
  def fingertips_pos(self):
    return observable.MJCFFeature('xpos', self._entity.fingertip_sites)
