"""D'Kitty Orient: turn in place to face a target.

ROBEL's task: docs/robel_reference.md section 2.6.
"""

import dataclasses
import math

from dm_control.composer import variation
from dm_control.composer.variation import distributions
import numpy as np

from robel_dm import constants, geometry, randomization, registry
from robel_dm.entities import dkitty
from robel_dm.tasks import base, dkitty_common

_EPISODE_STEPS = 80  # 8 s at 10 Hz.
_UPRIGHT = dkitty_common.Upright(threshold=0.9, reward=2.0, falling_reward=-500)


@dataclasses.dataclass(frozen=True)
class OrientReward:
  """ROBEL's Orient reward constants (a = facing error, rad; u = upright;
  c = horizontal distance from the start, m).

  Attributes:
    alignment_weight: `alignment_error_cost` is -weight * a.
    center_distance_weight: `center_distance_cost` is -weight * c.
    bonus_small, bonus_small_angle: paid once when a is below the angle or
      u above `bonus_upright` (ROBEL's logical OR).
    bonus_big, bonus_big_angle: paid when a is below the angle and u above
      `bonus_upright`.
    bonus_upright: the uprightness the bonuses ask for.
  """

  alignment_weight: float = 4.0
  center_distance_weight: float = 4.0
  bonus_small: float = 5.0
  bonus_small_angle: float = 0.26
  bonus_big: float = 10.0
  bonus_big_angle: float = 0.087
  bonus_upright: float = 0.96


REWARD = OrientReward()

# The target stands this far from the origin, m, at heading angle + pi/2.
_TARGET_DISTANCE = 1.0
_TARGET_MARKER = dkitty_common.Marker(
  'target', size=(0.05, 0.1), rgba=(0.9, 0.2, 0.2, 1), height=0.1
)

# OrientRandom: initial heading and target heading, rad.
_RANDOM_INITIAL_YAW = distributions.Uniform(-np.pi / 3, np.pi / 3)
_RANDOM_TARGET_YAW = distributions.Uniform(2 * np.pi / 3, 4 * np.pi / 3)


class OrientTask(base.RobelTask):
  """Turn to face a target one metre away, staying upright."""

  FEATURES = {
    **dkitty_common.FEATURES,
    'current_facing': 2,
    'desired_facing': 2,
    'angle_error': 1,
  }
  DEFAULT_OBSERVATION_KEYS = dkitty_common.DEFAULT_OBSERVATION_KEYS + (
    'current_facing',
    'desired_facing',
  )
  REWARD_TERMS = (
    'upright',
    'falling',
    'alignment_error_cost',
    'center_distance_cost',
    'bonus_small',
    'bonus_big',
  )
  DEFAULT_REWARD = REWARD

  def __init__(
    self,
    *,
    initial_yaw=0.0,
    target_yaw=np.pi,
    terrain: bool = False,
    **options,
  ):
    """Builds the floor, the robot, the target and the task.

    Args:
      initial_yaw: the robot's heading at reset (rad, or a Variation);
        0 faces +y.
      target_yaw: heading of the target from the origin (rad, or a
        Variation), in the same convention.
      terrain: turn on ROBEL's random heightfield instead of a plane.
      **options: `base.TaskOptions` fields (`dynamics`,
        `observation_noise`, `observation_keys`, `action_bounds`, `reward`).
    """
    self._kitty = dkitty_common.KittyParts(terrain=terrain, upright=_UPRIGHT)
    self._target = self._kitty.add_target(_TARGET_MARKER)
    self._initial_yaw = initial_yaw
    self._target_yaw = target_yaw
    self._angle_error = 0.0
    super().__init__(
      self._kitty.task_scene(_EPISODE_STEPS), base.TaskOptions(**options)
    )
    self._kitty.bind_features(self)
    self._facing_features = self.feature_span('current_facing', 'angle_error')

  @property
  def target(self) -> np.ndarray:
    """The target's position on the floor, m."""
    return self._target.position.copy()

  def after_compile(self, physics, random_state) -> None:
    super().after_compile(physics, random_state)
    self._kitty.after_compile(physics)

  def _initialize_state(self, physics, random_state) -> None:
    yaw = float(
      variation.evaluate(self._initial_yaw, random_state=random_state)
    )
    target_yaw = float(
      variation.evaluate(self._target_yaw, random_state=random_state)
    )
    # Headings count from +y, so a heading h points along angle h + pi/2.
    self._target.place(target_yaw + np.pi / 2, _TARGET_DISTANCE)
    self._kitty.reset(physics, random_state, dkitty.STANDING_POSE, yaw=yaw)

  def _compute_features(self, physics) -> None:
    del physics
    self._kitty.update(self._sensed_qpos, self._sensed_qvel)
    self._target.track(self._robot_io)
    torso = self._kitty.torso
    facing = torso.facing
    to_target = self._target.position - torso.position[:2]
    distance = geometry.norm(to_target)
    desired = to_target / distance if distance > 0 else to_target
    cosine = min(max(geometry.cosine(facing, desired), -1.0), 1.0)
    self._angle_error = math.acos(cosine)
    self._facing_features[:] = (*facing, *desired, self._angle_error)

  def _compute_reward_terms(self) -> dict[str, float]:
    angle_error = self._angle_error
    upright = self._kitty.torso.upright > self.reward_constants.bonus_upright
    # Either condition pays the small bonus once (ROBEL's logical OR).
    small = angle_error < self.reward_constants.bonus_small_angle or upright
    return {
      **self._kitty.upright_terms(),
      'alignment_error_cost': -self.reward_constants.alignment_weight
      * angle_error,
      'center_distance_cost': -self.reward_constants.center_distance_weight
      * geometry.norm(self._kitty.torso.position[:2]),
      'bonus_small': self.reward_constants.bonus_small if small else 0.0,
      'bonus_big': self.reward_constants.bonus_big
      if self._facing_target()
      else 0.0,
    }

  def _facing_target(self) -> bool:
    """Facing the target and upright: `bonus_big` and success."""
    return (
      self._angle_error < self.reward_constants.bonus_big_angle
      and self._kitty.torso.upright > self.reward_constants.bonus_upright
    )

  def _compute_score(self) -> float:
    return 1.0 - self._angle_error / np.pi

  def _compute_success(self) -> bool:
    return self._facing_target()

  def _compute_failure(self) -> bool:
    return self._kitty.fallen()


@registry.DKITTY.add(registry.FIXED)
def orient_fixed(**kwargs) -> OrientTask:
  """Turn around: from facing +y to a target directly behind."""
  return OrientTask(initial_yaw=0.0, target_yaw=np.pi, **kwargs)


@registry.DKITTY.add(registry.RANDOM)
def orient_random(**kwargs) -> OrientTask:
  """Random initial heading and a target roughly behind."""
  return OrientTask(
    initial_yaw=_RANDOM_INITIAL_YAW, target_yaw=_RANDOM_TARGET_YAW, **kwargs
  )


@registry.DKITTY.add(registry.RANDOM_DYNAMICS)
def orient_random_dynamics(**kwargs) -> OrientTask:
  """orient_random on random terrain with random dynamics and noise."""
  return orient_random(
    terrain=True,
    dynamics=randomization.DKITTY_LOCOMOTION,
    observation_noise=constants.OBSERVATION_NOISE_FRACTION,
    **kwargs,
  )
