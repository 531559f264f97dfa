"""D'Kitty Stand: stand up straight from a crouch.

ROBEL's task: docs/robel_reference.md section 2.5.
"""

from dm_control.composer import variation
import numpy as np

from robel_dm import constants, randomization, registry
from robel_dm.entities import dkitty
from robel_dm.tasks import base, dkitty_common

_EPISODE_STEPS = 80  # 8 s at 10 Hz.
_UPRIGHT = dkitty_common.Upright(threshold=0.0, reward=2.0, falling_reward=-100)

# Reward weights and thresholds (rad, m).
_POSE_ERROR_WEIGHT = 4.0
_CENTER_DISTANCE_WEIGHT = 2.0
_BONUS_SMALL, _BONUS_SMALL_ERROR = 5.0, np.pi / 6
_BONUS_BIG, _BONUS_BIG_ERROR, _BONUS_BIG_UPRIGHT = 10.0, np.pi / 12, 0.9
# Score: points fall linearly to 0 at this mean |joint error|, rad.
_POINTS_ERROR_SCALE = np.pi / 3

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

  def __init__(
    self,
    *,
    initial_pose=dkitty.CROUCHED_POSE,
    terrain: bool = False,
    settle_substeps: int = SETTLE_SUBSTEPS,
    dynamics: randomization.DynamicsRanges | None = None,
    observation_noise: float = 0.0,
    observation_keys: tuple[str, ...] | None = None,
    action_bounds: str = 'raise',
  ):
    """Builds the floor, the robot and the task.

    Args:
      initial_pose: 12 leg joint angles (or a Variation) at reset, rad; None
        draws each joint uniformly over its action range (ROBEL's Random).
      terrain: stand on ROBEL's random heightfield instead of a plane.
      settle_substeps: physics steps a reset runs, commanding the initial
        pose, before the episode starts (ROBEL: 140, i.e. 0.35 s).
      dynamics: per-episode dynamics ranges, or None.
      observation_noise: ROBEL's observation-noise fraction (leg joints).
      observation_keys: the agent's observation; ROBEL's default if None.
      action_bounds: 'raise' or 'clip' for actions outside [-1, 1].
    """
    self._kitty = dkitty_common.KittyParts(terrain=terrain, upright=_UPRIGHT)
    if settle_substeps < 0:
      raise ValueError(f'settle_substeps must be >= 0: {settle_substeps}')
    self._settle_substeps = settle_substeps
    self._initial_pose = initial_pose
    self._goal_pose = dkitty.STANDING_POSE
    self._abs_error = np.zeros(12)
    self._reference_start = np.zeros(12)
    super().__init__(
      **self._kitty.robel_task_arguments(),
      episode_steps=_EPISODE_STEPS,
      dynamics=dynamics,
      observation_noise=observation_noise,
      observation_keys=observation_keys,
      action_bounds=action_bounds,
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
      pose = random_state.uniform(self._range_low, self._range_high)
    else:
      pose = variation.evaluate(self._initial_pose, random_state=random_state)
    self._kitty.reset(physics, random_state, pose)
    # Let the robot settle on its legs, then start the clock at 0.
    # (dm_control's step(0) would still finish one pending step.)
    if self.settle_substeps:
      physics.step(self.settle_substeps)
    physics.data.time = 0.0
    physics.forward()
    self._reference_start = physics.bind(self.robot.joints).qpos.copy()

  def _compute(self, physics) -> tuple[float, ...]:
    upright_term, falling_term, self._failed = self._kitty.update(
      self._sensed_qpos, self._sensed_qvel
    )
    np.subtract(
      self._goal_pose, self._sensed_qpos, out=self._pose_error_feature
    )
    error = np.abs(self._goal_pose - self._qpos, out=self._abs_error)
    mean_error = float(np.dot(error, self._joint_weights))
    upright = self._kitty.torso.upright
    center_distance = base.norm(self._kitty.torso.position[:2])
    small = _BONUS_SMALL * upright if mean_error < _BONUS_SMALL_ERROR else 0.0
    big = (
      _BONUS_BIG
      if mean_error < _BONUS_BIG_ERROR and upright > _BONUS_BIG_UPRIGHT
      else 0.0
    )
    # ROBEL wrote max(), which makes the points <= 0 always; min() is meant.
    points = 1.0 - min(mean_error / _POINTS_ERROR_SCALE, 1.0)
    self._score[...] = points * upright
    self._success[...] = big > 0
    return (
      upright_term,
      falling_term,
      -_POSE_ERROR_WEIGHT * mean_error,
      -_CENTER_DISTANCE_WEIGHT * center_distance,
      small,
      big,
    )


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
