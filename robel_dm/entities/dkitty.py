"""The D'Kitty: a 12-DoF quadruped of Dynamixel servos.

ROBEL's model: docs/robel_reference.md section 3.4.
"""

from dm_control import composer, mjcf
from dm_control.composer.observation import observable
import numpy as np

from robel_dm.entities import limits, servo_robot

# Joints in action order; motor IDs are the digits (docs/robel_reference.md
# sections 3.4, 4.1).
# Legs: front right, front left, back left, back right; the robot faces +y.
JOINT_NAMES = (
  'FRJ10', 'FRJ11', 'FRJ12',
  'FLJ20', 'FLJ21', 'FLJ22',
  'BLJ30', 'BLJ31', 'BLJ32',
  'BRJ40', 'BRJ41', 'BRJ42',
)  # fmt: skip
FOOT_SITE_NAMES = ('FRfoot', 'FLfoot', 'BLfoot', 'BRfoot')

# ROBEL's per-joint velocity limit used by the action clamp, rad/s.
MAX_JOINT_SPEED = np.pi

# ROBEL defines safety counters for the D'Claw only; its paper applies them to
# every robot with per-joint limits. robel_dm's D'Kitty limits: the D'Claw's
# 5 degree margin, but to the mechanical joint range (the standing pose lies
# on the action range's bounds), ROBEL's D'Kitty joint-speed range (pi rad/s),
# and 1 A, a sustained high load for an X-series servo (stall is 1.3-2.3 A).
SAFETY_LIMITS = limits.SafetyLimits(
  position_margin=np.deg2rad(5.0),
  max_speed=np.pi,
  max_current=1000.0,
  position_range='joint',
)

# The standing pose (all joints straight) and ROBEL's StandFixed start, rad.
STANDING_POSE = np.zeros(12)
CROUCHED_POSE = np.tile([0.0, np.pi / 4, -np.pi / 2], 4)

# ROBEL's D'Kitty frame origin: its root position is measured from here, m.
ROBEL_FRAME_ORIGIN = np.array([0.0, 0.0, 0.3])


class DKitty(servo_robot.ServoRobot):
  """The D'Kitty quadruped. Attach it with a free joint (`add_free_entity`)."""

  MODEL = ('dkitty', 'dkitty.xml')
  DEFAULT_NAME = 'dkitty'
  JOINT_NAMES = JOINT_NAMES
  MAX_JOINT_SPEED = MAX_JOINT_SPEED
  SAFETY_LIMITS = SAFETY_LIMITS

  def _find_parts(self, root: mjcf.RootElement) -> None:
    (self._torso,) = servo_robot.find_all(root, 'body', ('torso',))
    self._foot_sites = servo_robot.find_all(root, 'site', FOOT_SITE_NAMES)

  def _build_observables(self) -> 'DKittyObservables':
    return DKittyObservables(self)

  @property
  def torso(self) -> mjcf.Element:
    return self._torso

  @property
  def root_body(self) -> mjcf.Element:
    return self._torso

  @property
  def foot_sites(self) -> tuple[mjcf.Element, ...]:
    return self._foot_sites


class DKittyObservables(servo_robot.JointObservables):
  """Joint, torso and foot observables (disabled until a task enables them)."""

  @composer.observable
  def torso_pos(self):
    return observable.MJCFFeature('xpos', self._entity.torso)

  @composer.observable
  def torso_xmat(self):
    return observable.MJCFFeature('xmat', self._entity.torso)

  @composer.observable
  def feet_pos(self):
    return observable.MJCFFeature('xpos', self._entity.foot_sites)
