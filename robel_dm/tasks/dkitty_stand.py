"""D'Kitty Stand: stand up straight from a crouch.

ROBEL's task: docs/robel_reference.md section 2.5.
"""

import dataclasses

from dm_control.composer import variation
import numpy as np

from robel_dm import constants, geometry, numeric, randomization, registry
from robel_dm.entities import dkitty
from robel_dm.tasks import base, dkitty_common

_EPISODE_STEPS = 80  # 8 s at 10 Hz.
_UPRIGHT = dkitty_common.Upright(threshold=0.0, reward=2.0, falling_reward=-100)


@dataclasses.dataclass(frozen=True)
class StandReward:
  """ROBEL's Stand reward constants (e = mean |joint error|, rad; u =
  upright; c = horizontal distance from the start, m).

  Attributes:
    pose_error_weight: `pose_error_cost` is -weight * e.
    center_distance_weight: `center_distance_cost` is -weight * c.
    bonus_small, bonus_small_error: u * bonus_small when e is below the
      error.
    bonus_big, bonus_big_error, bonus_big_upright: paid when e is below the
      error and u above the uprightness.
    points_error_scale: the points fall linearly to 0 at this e, rad.
  """

  pose_error_weight: float = 4.0
  center_distance_weight: float = 2.0
  bonus_small: float = 5.0
  bonus_small_error: float = np.pi / 6
  bonus_big: float = 10.0
  bonus_big_error: float = np.pi / 12
  bonus_big_upright: float = 0.9
  points_error_scale: float = np.pi / 3


REWARD = StandReward()

# Speed of the reference controller's standing-up ramp, rad/s.
_REFERENCE_SPEED = 0.8

# Settling at reset: ROBEL commands the initial pose for one control step
# (40 substeps) and then runs 100 more substeps, 0.35 s in all.
SETTLE_SUBSTEPS = 40 + 100


class StandTask(base.RobelTask):
  """Reach the standing pose (all joints 0) and stay upright."""

  FEATURES = {**dkitty_common.FEATURES, 'pose_error': 12}
  DEFAULT_OBSERVATION_KEYS = dkitty_common.DEFAULT_OBSERVATION_KEYS + (
    'pose_error',
  )
  REWARD_TERMS = (
    'upright',
    'falling',
    'pose_error_cost',
    'center_distance_cost',
    'bonus_small',
    'bonus_big',
  )
  DEFAULT_REWARD = REWARD

  def __init__(
    self,
    *,
    initial_pose=dkitty.CROUCHED_POSE,
    terrain: bool = False,
    settle_substeps: int = SETTLE_SUBSTEPS,
    **options,
  ):
    """Builds the floor, the robot and the task.

    Args:
      initial_pose: 12 leg joint angles (or a Variation) at reset, rad; None
        draws each joint uniformly over its action range (ROBEL's Random).
      terrain: stand on ROBEL's random heightfield instead of a plane.
      settle_substeps: physics steps a reset runs, commanding the initial
        pose, before the episode starts (ROBEL: 140, i.e. 0.35 s).
      **options: `base.TaskOptions` fields (`dynamics`,
        `observation_noise`, `observation_keys`, `action_bounds`, `reward`).
    """
    self._kitty = dkitty_common.KittyParts(terrain=terrain, upright=_UPRIGHT)
    if not numeric.is_integer(settle_substeps) or settle_substeps < 0:
      raise ValueError(
        f'settle_substeps must be an integer >= 0, got {settle_substeps!r}'
      )
    self._settle_substeps = settle_substeps
    self._initial_pose = initial_pose
    self._goal_pose = dkitty.STANDING_POSE
    self._abs_error = np.zeros(12)
    self._reference_start = np.zeros(12)
    self._mean_error = 0.0
    super().__init__(
      self._kitty.task_scene(_EPISODE_STEPS), base.TaskOptions(**options)
    )
    self._kitty.bind_features(self)
    self._pose_error_feature = self._features['pose_error']
    self._joint_weights = np.full(12, 1 / 12)  # Means as dot products.

  @property
  def settle_substeps(self) -> int:
    return self._settle_substeps

  def after_compile(self, physics, random_state) -> None:
    super().after_compile(physics, random_state)
    self._kitty.after_compile(physics)

  def reference_action(self, physics) -> np.ndarray:
    """Commands a ramp from the pose at reset to the standing pose.

    The command moves at `_REFERENCE_SPEED`; commanding the standing pose at
    once (the action clamp's pi rad/s) tips the robot over in simulation.
    """
    elapsed = physics.data.time
    start = self._reference_start
    ramp = np.clip(
      self._goal_pose - start,
      -_REFERENCE_SPEED * elapsed,
      _REFERENCE_SPEED * elapsed,
    )
    return self.normalize_joint_targets(start + ramp)

  def _initialize_state(self, physics, random_state) -> None:
    if self._initial_pose is None:
      action_map = self._action_map
      pose = random_state.uniform(action_map.low, action_map.high)
    else:
      pose = self.checked_pose(
        physics,
        'initial_pose',
        variation.evaluate(self._initial_pose, random_state=random_state),
      )
    self._kitty.reset(physics, random_state, pose)
    # Let the robot settle on its legs, then start the clock at 0.
    # (dm_control's step(0) would still finish one pending step.)
    if self.settle_substeps:
      physics.step(self.settle_substeps)
    physics.data.time = 0.0
    physics.forward()
    self._reference_start = physics.bind(self.robot.joints).qpos.copy()

  def _compute_features(self, physics) -> None:
    del physics
    self._kitty.update(self._sensed_qpos, self._sensed_qvel)
    np.subtract(
      self._goal_pose, self._sensed_qpos, out=self._pose_error_feature
    )
    error = np.abs(self._goal_pose - self._qpos, out=self._abs_error)
    self._mean_error = geometry.dot(error, self._joint_weights)

  def _compute_reward_terms(self) -> dict[str, float]:
    error = self._mean_error
    torso = self._kitty.torso
    upright = torso.upright
    return {
      **self._kitty.upright_terms(),
      'pose_error_cost': -self.reward_constants.pose_error_weight * error,
      'center_distance_cost': -self.reward_constants.center_distance_weight
      * geometry.norm(torso.position[:2]),
      'bonus_small': (
        self.reward_constants.bonus_small * upright
        if error < self.reward_constants.bonus_small_error
        else 0.0
      ),
      'bonus_big': self.reward_constants.bonus_big if self._standing() else 0.0,
    }

  def _standing(self) -> bool:
    """Close to the standing pose and upright: `bonus_big` and success."""
    return (
      self._mean_error < self.reward_constants.bonus_big_error
      and self._kitty.torso.upright > self.reward_constants.bonus_big_upright
    )

  def _compute_score(self) -> float:
    # ROBEL wrote max(), which makes the points <= 0 always; min() is meant.
    points = 1.0 - min(
      self._mean_error / self.reward_constants.points_error_scale, 1.0
    )
    return points * self._kitty.torso.upright

  def _compute_success(self) -> bool:
    return self._standing()

  def _compute_failure(self) -> bool:
    return self._kitty.fallen()


@registry.DKITTY.add(registry.FIXED)
def stand_fixed(**kwargs) -> StandTask:
  """Stand up from ROBEL's crouch [0, pi/4, -pi/2] per leg."""
  return StandTask(**kwargs)


@registry.DKITTY.add(registry.RANDOM)
def stand_random(**kwargs) -> StandTask:
  """Stand up from a random leg pose."""
  return StandTask(initial_pose=None, **kwargs)


@registry.DKITTY.add(registry.RANDOM_DYNAMICS)
def stand_random_dynamics(**kwargs) -> StandTask:
  """stand_random on random terrain with random dynamics and noise."""
  return stand_random(
    terrain=True,
    dynamics=randomization.DKITTY_STAND,
    observation_noise=constants.OBSERVATION_NOISE_FRACTION,
    **kwargs,
  )
