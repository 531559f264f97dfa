"""D'Kitty Walk: walk to a target while facing it.

ROBEL's task: docs/robel_reference.md section 2.7.
"""

import dataclasses

from dm_control.composer import variation
from dm_control.composer.variation import distributions
import numpy as np

from robel_dm import constants, geometry, randomization, registry
from robel_dm.entities import dkitty
from robel_dm.tasks import base, dkitty_common

_EPISODE_STEPS = 160  # 16 s at 10 Hz.
# The target's disc and ROBEL's heading marker (the heading target is the
# target itself).
_TARGET_MARKERS = (
  dkitty_common.Marker(
    'target', size=(0.5, 0.005), rgba=(0.2, 0.8, 0.3, 0.6), height=0.005
  ),
  dkitty_common.Marker(
    'heading', size=(0.05, 0.25), rgba=(0.9, 0.6, 0.1, 1), height=0.25
  ),
)
_UPRIGHT = dkitty_common.Upright(threshold=0.9, reward=1.0, falling_reward=-500)


@dataclasses.dataclass(frozen=True)
class WalkReward:
  """ROBEL's Walk reward constants (D = distance to the target, m; h =
  heading cosine).

  Attributes:
    target_distance_weight: `target_dist_cost` is -weight * D.
    heading_weight, heading_threshold: the `heading` term is
      weight * (h - threshold) / (1 - threshold); facing the target means
      h above the threshold.
    bonus_small: paid once when near the target or facing it (ROBEL's
      logical OR).
    bonus_big: paid when near the target and facing it.
    bonus_distance: near the target means D below this, m.
  """

  target_distance_weight: float = 4.0
  heading_weight: float = 2.0
  heading_threshold: float = 0.9
  bonus_small: float = 5.0
  bonus_big: float = 10.0
  bonus_distance: float = 0.5


REWARD = WalkReward()

# WalkRandom: target distance, m, and heading offset from straight ahead, rad.
_RANDOM_DISTANCE = distributions.Uniform(1.0, 2.0)
_RANDOM_ANGLE = distributions.Uniform(-np.pi / 3, np.pi / 3)


class WalkTask(base.RobelTask):
  """Walk to a target on the floor, facing it, staying upright."""

  FEATURES = {
    **dkitty_common.FEATURES,
    'heading': 1,
    'target_pos': 2,
    'target_error': 2,
  }
  DEFAULT_OBSERVATION_KEYS = dkitty_common.DEFAULT_OBSERVATION_KEYS + (
    'heading',
    'target_error',
  )
  REWARD_TERMS = (
    'upright',
    'falling',
    'target_dist_cost',
    'heading',
    'bonus_small',
    'bonus_big',
  )
  DEFAULT_REWARD = REWARD

  def __init__(
    self,
    *,
    target_distance=2.0,
    target_angle=0.0,
    terrain: bool = False,
    **options,
  ):
    """Builds the floor, the robot, the target and the task.

    Args:
      target_distance: distance of the target from the start, m (or a
        Variation).
      target_angle: direction of the target from straight ahead (+y), rad
        (or a Variation), counter-clockwise.
      terrain: walk on ROBEL's random heightfield instead of a plane.
      **options: `base.TaskOptions` fields (`dynamics`,
        `observation_noise`, `observation_keys`, `action_bounds`, `reward`).
    """
    self._kitty = dkitty_common.KittyParts(terrain=terrain, upright=_UPRIGHT)
    self._target = self._kitty.add_target(*_TARGET_MARKERS)
    self._target_distance = target_distance
    self._target_angle = target_angle
    self._distance = 0.0
    self._heading = 0.0
    super().__init__(
      self._kitty.task_scene(_EPISODE_STEPS), base.TaskOptions(**options)
    )
    self._kitty.bind_features(self)
    self._target_features = self.feature_span('heading', 'target_error')

  @property
  def target(self) -> np.ndarray:
    """The target's position on the floor, m."""
    return self._target.position.copy()

  def after_compile(self, physics, random_state) -> None:
    super().after_compile(physics, random_state)
    self._kitty.after_compile(physics)

  def _initialize_state(self, physics, random_state) -> None:
    distance = float(
      variation.evaluate(self._target_distance, random_state=random_state)
    )
    angle = np.pi / 2 + float(
      variation.evaluate(self._target_angle, random_state=random_state)
    )
    self._target.place(angle, distance)
    self._kitty.reset(physics, random_state, dkitty.STANDING_POSE)

  def _compute_features(self, physics) -> None:
    del physics
    self._kitty.update(self._sensed_qpos, self._sensed_qvel)
    self._target.track(self._robot_io)
    target = self._target.position
    torso = self._kitty.torso
    target_error = target - torso.position[:2]
    tracked_heading = self._robot_io.tracked_heading()
    towards = (
      target_error
      if tracked_heading is None
      else tracked_heading - torso.position[:2]
    )
    self._heading = geometry.cosine(torso.facing, towards)
    self._target_features[:] = (self._heading, *target, *target_error)
    self._distance = geometry.norm(target_error)

  def _compute_reward_terms(self) -> dict[str, float]:
    near = self._distance < self.reward_constants.bonus_distance
    facing = self._heading > self.reward_constants.heading_threshold
    threshold = self.reward_constants.heading_threshold
    return {
      **self._kitty.upright_terms(),
      'target_dist_cost': -self.reward_constants.target_distance_weight
      * self._distance,
      'heading': self.reward_constants.heading_weight
      * (self._heading - threshold)
      / (1 - threshold),
      # Either condition pays the small bonus once (ROBEL's logical OR).
      'bonus_small': self.reward_constants.bonus_small
      if near or facing
      else 0.0,
      'bonus_big': self.reward_constants.bonus_big if near and facing else 0.0,
    }

  def _compute_score(self) -> float:
    return -self._distance

  def _compute_success(self) -> bool:
    return (
      self._distance < self.reward_constants.bonus_distance
      and self._heading > self.reward_constants.heading_threshold
    )

  def _compute_failure(self) -> bool:
    return self._kitty.fallen()


@registry.DKITTY.add(registry.FIXED)
def walk_fixed(**kwargs) -> WalkTask:
  """Walk 2 m straight ahead."""
  return WalkTask(target_distance=2.0, target_angle=0.0, **kwargs)


@registry.DKITTY.add(registry.RANDOM)
def walk_random(**kwargs) -> WalkTask:
  """Walk 1-2 m to a target within 60 degrees of straight ahead."""
  return WalkTask(
    target_distance=_RANDOM_DISTANCE, target_angle=_RANDOM_ANGLE, **kwargs
  )


@registry.DKITTY.add(registry.RANDOM_DYNAMICS)
def walk_random_dynamics(**kwargs) -> WalkTask:
  """walk_random on random terrain with random dynamics and noise."""
  return walk_random(
    terrain=True,
    dynamics=randomization.DKITTY_LOCOMOTION,
    observation_noise=constants.OBSERVATION_NOISE_FRACTION,
    **kwargs,
  )
