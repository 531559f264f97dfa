"""D'Claw Pose: drive the nine joints to a goal pose.

ROBEL's task: docs/robel_reference.md section 2.1.
"""

import dataclasses
import math

from dm_control.composer import variation
from dm_control.composer.variation import distributions
import numpy as np

from robel_dm import constants, geometry, randomization, registry
from robel_dm.arenas import station
from robel_dm.entities import dclaw
from robel_dm.tasks import base

_EPISODE_STEPS = 80  # 4 s at 20 Hz.


@dataclasses.dataclass(frozen=True)
class PoseReward:
  """ROBEL's Pose reward, score and success constants.

  Attributes:
    joint_vel_weight: weight of `joint_vel_cost`.
    fast_joint_speed: `joint_vel_cost` counts joints at least this fast,
      rad/s.
    points_error_scale: the points fall linearly to 0 at this mean |joint
      error|, rad.
    success_threshold: success is a mean |joint error| below this,
      averaged over the episode, rad.
  """

  joint_vel_weight: float = 0.1
  fast_joint_speed: float = np.pi
  points_error_scale: float = np.pi / 4
  success_threshold: float = np.deg2rad(10.0)


REWARD = PoseReward()

# A moving goal oscillates each joint at its own angular frequency, drawn
# from this range, rad/s, and cuts each joint's amplitude so that no joint's
# goal moves faster than _MAX_GOAL_SPEED, rad/s.
_NUM_JOINTS = 9
_GOAL_FREQUENCY = distributions.Uniform(
  np.full(_NUM_JOINTS, 0.5), np.full(_NUM_JOINTS, 2.0)
)
_MAX_GOAL_SPEED = np.pi / 6

# Joint speed of the reference controller's commands, rad/s: below the 1 rad/s
# of the velocity safety counter.
_REFERENCE_SPEED = 0.8

# ROBEL's random-pose sampler: the action ranges, except that the middle
# joints are never bent outwards (upper bound 0), rad.
_POSE_LOW = np.tile([-0.48, -np.pi / 3, -np.pi / 2], 3)
_POSE_HIGH = np.tile([0.48, 0.0, np.pi / 2], 3)
RANDOM_POSE = distributions.Uniform(_POSE_LOW, _POSE_HIGH)

# pose_fixed starts every episode from the same pose and chases the same goal
# (ROBEL's "Fixed" drew both at random each episode). Both poses lie inside
# the random sampler's box and keep the fingertips apart, rad.
FIXED_INITIAL_POSE = np.zeros(9)
FIXED_GOAL_POSE = np.array([0.3, -0.6, 0.9, -0.3, -0.6, 0.9, 0.0, -0.8, 1.1])


class PoseTask(base.RobelTask):
  """Match a static or oscillating goal pose of the claw's joints."""

  FEATURES = {'qpos': 9, 'qvel': 9, 'last_action': 9, 'qpos_error': 9}
  DEFAULT_OBSERVATION_KEYS = ('qpos', 'last_action', 'qpos_error')
  REWARD_TERMS = ('pose_error_cost', 'joint_vel_cost')
  DEFAULT_REWARD = REWARD

  def __init__(
    self,
    *,
    initial_pose=FIXED_INITIAL_POSE,
    goal_pose=FIXED_GOAL_POSE,
    goal_frequency=None,
    **options,
  ):
    """Builds the claw station and the task.

    Args:
      initial_pose: 9 joint angles (or a Variation of them) to start from.
      goal_pose: 9 joint angles (or a Variation) of the goal.
      goal_frequency: None for a static goal. Otherwise angular frequencies
        (rad/s: one per joint, or one for all; or a Variation of them): the
        claw starts halfway between `initial_pose` and `goal_pose` and each
        joint's goal oscillates between them at its own frequency, as in
        ROBEL's PoseRandom, its amplitude cut so that it moves no faster
        than `_MAX_GOAL_SPEED`.
      **options: `base.TaskOptions` fields (`dynamics`,
        `observation_noise`, `observation_keys`, `action_bounds`, `reward`).
    """
    arena = station.ClawStation(
      mount_height=station.MOUNT_HEIGHT_POSE, show_goal=False
    )
    claw = dclaw.DClaw()
    arena.attach_claw(claw)
    self._initial_pose = initial_pose
    self._goal_pose = goal_pose
    self._goal_frequency = goal_frequency
    self._goal_center = np.zeros(9)
    self._goal_amplitude = np.zeros(9)
    self._frequency = np.zeros(9)
    self._goal_moves = False
    self._phase = np.zeros(9)
    self._goal = np.zeros(9)
    self._error = np.zeros(9)
    self._true_error = self._error  # The goal minus the true joint angles.
    self._abs_error = np.zeros(9)
    self._mean_error = 0.0
    self._speed_squared = np.zeros(9)
    self._fast = np.zeros(9, dtype=bool)
    self._joint_weights = np.full(9, 1 / 9)  # Means as dot products (faster).
    scene = base.Scene(
      arena=arena,
      robot=claw,
      control_timestep=constants.CONTROL_TIMESTEP_FAST,
      episode_steps=_EPISODE_STEPS,
      randomizer_targets=randomization.Targets(
        joints=claw.joints, actuators=claw.actuators
      ),
    )
    super().__init__(scene, base.TaskOptions(**options))
    self._qpos_feature = self._features['qpos']
    self._qvel_feature = self._features['qvel']
    self._qpos_error_feature = self._features['qpos_error']

  @property
  def goal(self) -> np.ndarray:
    """The current goal pose, rad."""
    return self._goal.copy()

  @property
  def goal_frequency(self) -> np.ndarray:
    """Each joint's goal oscillation frequency this episode, rad/s (zeros
    for a static goal)."""
    return self._frequency.copy()

  @property
  def goal_amplitude(self) -> np.ndarray:
    """Each joint's goal oscillation amplitude this episode, rad."""
    return self._goal_amplitude.copy()

  def reference_action(self, physics) -> np.ndarray:
    """Moves every joint towards the goal, slower than the safety limit.

    Commanding the goal outright would move the joints at the action clamp's
    2pi/3 rad/s, which the velocity safety counter flags (limit 1 rad/s).
    """
    del physics
    max_step = _REFERENCE_SPEED * self.control_timestep
    qpos = self._robot_qpos
    step = np.clip(self._goal - qpos, -max_step, max_step)
    return self.normalize_joint_targets(qpos + step)

  def _initialize_state(self, physics, random_state) -> None:
    pose_a = self.checked_pose(
      physics,
      'initial_pose',
      variation.evaluate(self._initial_pose, random_state=random_state),
    )
    pose_b = self.checked_pose(
      physics,
      'goal_pose',
      variation.evaluate(self._goal_pose, random_state=random_state),
    )
    if self._goal_frequency is None:
      initial = pose_a
      self._goal_center[:] = pose_b
      self._goal_amplitude[:] = 0.0
      self._frequency[:] = 0.0
    else:
      self._frequency[:] = variation.evaluate(
        self._goal_frequency, random_state=random_state
      )
      if not np.all(self._frequency > 0):
        raise ValueError(
          f'goal frequencies must be positive: {self._frequency.tolist()}'
        )
      initial = (pose_a + pose_b) / 2
      self._goal_center[:] = initial
      self._goal_amplitude[:] = np.minimum(
        np.abs(pose_b - pose_a) / 2, _MAX_GOAL_SPEED / self._frequency
      )
    self._goal_moves = self._goal_frequency is not None
    self._goal[:] = self._goal_center  # The goal at time 0.
    physics.bind(self.robot.joints).qpos = initial
    physics.bind(self.robot.actuators).ctrl = initial

  def _compute_features(self, physics) -> None:
    del physics
    goal = self._goal
    if self._goal_moves:
      phase = np.multiply(self._frequency, self._mjdata.time, out=self._phase)
      np.sin(phase, out=phase)
      np.multiply(self._goal_amplitude, phase, out=goal)
      goal += self._goal_center
    self._qpos_feature[:] = self._sensed_qpos
    self._qvel_feature[:] = self._sensed_qvel
    np.subtract(goal, self._sensed_qpos, out=self._qpos_error_feature)
    if self.observation_noise:  # Rewards use the true error.
      self._true_error = np.subtract(goal, self._qpos, out=self._error)
    else:
      self._true_error = self._qpos_error_feature
    abs_error = np.abs(self._true_error, out=self._abs_error)
    self._mean_error = geometry.dot(abs_error, self._joint_weights)

  def _compute_reward_terms(self) -> dict[str, float]:
    speed_squared = np.square(self._qvel, out=self._speed_squared)
    fast = np.greater_equal(
      speed_squared, self.reward_constants.fast_joint_speed**2, out=self._fast
    )
    return {
      'pose_error_cost': -geometry.norm(self._true_error),
      'joint_vel_cost': -self.reward_constants.joint_vel_weight
      * math.sqrt(geometry.dot(speed_squared, fast)),
    }

  def _compute_score(self) -> float:
    return 1.0 - min(
      self._mean_error / self.reward_constants.points_error_scale, 1.0
    )

  def _compute_success(self) -> bool:
    return (
      self._episode_mean(self._mean_error)
      < self.reward_constants.success_threshold
    )


@registry.DCLAW.add(registry.FIXED)
def pose_fixed(**kwargs) -> PoseTask:
  """A fixed goal pose from a fixed initial pose."""
  return PoseTask(**kwargs)


@registry.DCLAW.add(registry.RANDOM)
def pose_random(**kwargs) -> PoseTask:
  """A goal oscillating between two random poses, each joint at its own
  random frequency."""
  return PoseTask(
    initial_pose=RANDOM_POSE,
    goal_pose=RANDOM_POSE,
    goal_frequency=_GOAL_FREQUENCY,
    **kwargs,
  )


@registry.DCLAW.add(registry.RANDOM_DYNAMICS)
def pose_random_dynamics(**kwargs) -> PoseTask:
  """pose_random with randomized joint dynamics and observation noise."""
  return pose_random(
    dynamics=randomization.DCLAW_POSE,
    observation_noise=constants.OBSERVATION_NOISE_FRACTION,
    **kwargs,
  )
