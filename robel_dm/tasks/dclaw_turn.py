"""D'Claw Turn: turn a free valve to a goal angle.

ROBEL's task: docs/robel_reference.md section 2.2.
"""

import dataclasses
import math

from dm_control.composer import variation
from dm_control.composer.variation import distributions
import numpy as np

from robel_dm import constants, geometry, numeric, randomization, registry
from robel_dm.arenas import station
from robel_dm.entities import dclaw
from robel_dm.entities import valve as valve_lib
from robel_dm.tasks import base

_EPISODE_STEPS = 40  # 4 s at 10 Hz.
_SUCCESS_THRESHOLD = 0.1  # |angle error| at the last step, rad.


@dataclasses.dataclass(frozen=True)
class TurnReward:
  """ROBEL's Turn/Screw reward constants (d = |angle error|, rad).

  Attributes:
    target_dist_weight: `target_dist_cost` is -weight * d.
    fast_joint_speed: `joint_vel_cost` counts claw joints at least this
      fast, rad/s.
    bonus_small, bonus_small_distance: paid when d is below the distance.
    bonus_big, bonus_big_distance: likewise.
  """

  target_dist_weight: float = 5.0
  fast_joint_speed: float = 0.5
  bonus_small: float = 10.0
  bonus_small_distance: float = 0.25
  bonus_big: float = 50.0
  bonus_big_distance: float = 0.10


REWARD = TurnReward()

# The valve's angle range for observation noise (it has no velocity range, so
# ROBEL adds no velocity noise), rad.
_VALVE_ANGLE_WIDTH = 2 * np.pi

SUCCESS_AT_FINAL_STEP = 'final'
SUCCESS_ON_MEAN_ERROR = 'mean'

# TurnRandom: initial angle and goal offset from pi, rad.
_RANDOM_INITIAL_ANGLE = distributions.Uniform(-np.pi / 3, np.pi / 3)
_RANDOM_GOAL_ANGLE = distributions.Uniform(2 * np.pi / 3, 4 * np.pi / 3)


def _check_threshold(success_threshold) -> None:
  if not (numeric.is_finite(success_threshold) and success_threshold > 0):
    raise ValueError(
      'success_threshold must be a positive number of rad, got '
      f'{success_threshold!r}'
    )


class TurnTask(base.RobelTask):
  """Turn the valve to a goal angle; the goal may move at a fixed velocity."""

  FEATURES = {
    'claw_qpos': 9,
    'claw_qvel': 9,
    'object_x': 1,
    'object_y': 1,
    'object_qvel': 1,
    'last_action': 9,
    'target_error': 1,
    # Not in ROBEL's observation: the moving goal's velocity (rad/s), for
    # studies of what Screw Random needs (observation_keys=...).
    'goal_velocity': 1,
  }
  DEFAULT_OBSERVATION_KEYS = (
    'claw_qpos', 'object_x', 'object_y', 'last_action', 'target_error'
  )  # fmt: skip
  REWARD_TERMS = (
    'target_dist_cost',
    'pose_diff_cost',
    'joint_vel_cost',
    'bonus_small',
    'bonus_big',
  )
  DEFAULT_REWARD = REWARD

  def __init__(
    self,
    *,
    valve: str = 'valve3',
    initial_angle=0.0,
    goal_angle=np.pi,
    goal_velocity=0.0,
    episode_steps: int = _EPISODE_STEPS,
    success_threshold: float = _SUCCESS_THRESHOLD,
    success_on: str = SUCCESS_AT_FINAL_STEP,
    dynamics: randomization.DynamicsRanges | None = None,
    **options,
  ):
    """Builds the claw station with a valve, and the task.

    Args:
      valve: 'valve3' or 'valve4'.
      initial_angle: valve angle at reset (rad, or a Variation).
      goal_angle: goal angle at reset (rad, or a Variation), wrapped to
        [-pi, pi); None starts the goal at the valve's initial angle.
      goal_velocity: rate the goal moves at (rad/s, or a Variation); the
        moving goal is not wrapped, the angle error always is.
      episode_steps: control steps per episode.
      success_threshold: |angle error| below which the task succeeds, rad.
      success_on: 'final' judges the error at the current (finally the last)
        step, 'mean' the mean |error| of the episode so far.
      dynamics: per-episode dynamics ranges, or None.
      **options: the other `base.TaskOptions` fields
        (`observation_noise`, `observation_keys`, `action_bounds`,
        `reward`).

    Raises:
      ValueError: for an unknown valve or `success_on`, or a
        `success_threshold` that is not a positive number.
    """
    if success_on not in (SUCCESS_AT_FINAL_STEP, SUCCESS_ON_MEAN_ERROR):
      raise ValueError(f'success_on must be final or mean: {success_on!r}')
    _check_threshold(success_threshold)
    arena = station.ClawStation(mount_height=station.MOUNT_HEIGHT_VALVE)
    claw = dclaw.DClaw()
    arena.attach_claw(claw)
    self._valve = valve_lib.Valve(variant=valve)
    arena.attach(self._valve)
    self._initial_angle = initial_angle
    self._goal_angle = goal_angle
    self._goal_velocity = goal_velocity
    self._success_threshold = success_threshold
    self._success_on_mean = success_on == SUCCESS_ON_MEAN_ERROR
    self._goal_start = 0.0
    self._episode_initial_angle = 0.0
    self._velocity = 0.0
    self._distance = 0.0
    self._goal = 0.0
    scene = base.Scene(
      arena=arena,
      robot=claw,
      control_timestep=constants.CONTROL_TIMESTEP,
      episode_steps=episode_steps,
      extra_sensed_joints=(self._valve.hinge,),
      extra_position_widths=(_VALVE_ANGLE_WIDTH,),
      extra_velocity_widths=(0.0,),
      randomizer_targets=randomization.Targets(
        joints=claw.joints + (self._valve.hinge,),
        actuators=claw.actuators,
        mount=arena.mount,
        colored_geoms=(arena.mount_geom,) + self._valve.valve_geoms,
      ),
    )
    super().__init__(scene, base.TaskOptions(dynamics=dynamics, **options))
    self._claw_qpos_feature = self._features['claw_qpos']
    self._claw_qvel_feature = self._features['claw_qvel']
    self._object_features = self.feature_span('object_x', 'object_qvel')
    self._target_error_feature = self._features['target_error']
    self._goal_velocity_feature = self._features['goal_velocity']
    self._diff = np.zeros(len(claw.joints))

  @property
  def valve(self) -> valve_lib.Valve:
    return self._valve

  def auxiliary_joints(self) -> dict:
    """The valve (on a robot, its angle comes from motor 50)."""
    return {'valve': self._valve.hinge}

  @property
  def goal_is_an_angle(self) -> bool:
    return True

  @property
  def initial_angle(self) -> float:
    """The valve angle this episode started from (as drawn), rad."""
    return self._episode_initial_angle

  @property
  def goal_velocity(self) -> float:
    """The rate this episode's goal moves at, rad/s (as drawn)."""
    return self._velocity

  @property
  def goal(self) -> float:
    """The current goal angle, rad (unwrapped when the goal moves)."""
    return self._goal

  def after_compile(self, physics, random_state) -> None:
    super().after_compile(physics, random_state)
    goal = base.mocap_index(physics, self.arena.goal_body)
    self._goal_quat = physics.data.mocap_quat[goal]  # A view.

  def _initialize_state(self, physics, random_state) -> None:
    initial = float(
      variation.evaluate(self._initial_angle, random_state=random_state)
    )
    if self._goal_angle is None:
      self._goal_start = initial
    else:
      goal = variation.evaluate(self._goal_angle, random_state=random_state)
      self._goal_start = float(geometry.wrap_angle(goal))
    self._velocity = float(
      variation.evaluate(self._goal_velocity, random_state=random_state)
    )
    physics.bind(self.robot.joints).qpos = dclaw.RESET_POSE
    physics.bind(self.robot.actuators).ctrl = dclaw.RESET_POSE
    physics.bind(self._valve.hinge).qpos = initial
    self._episode_initial_angle = initial
    self._goal = self._goal_start
    self._show_goal()

  def _show_goal(self) -> None:
    half_yaw = self._goal / 2
    self._goal_quat[:] = (math.cos(half_yaw), 0.0, 0.0, math.sin(half_yaw))
    self._robot_io.show_goal(geometry.wrap_angle(self._goal))

  def _compute_features(self, physics) -> None:
    del physics
    person_goal = self._robot_io.goal_from_person()
    if person_goal is not None:
      # A person turns the guide; its angle is the goal.
      self._goal = person_goal
      self._show_goal()
    elif self._velocity:
      # The goal moves with time; time is a whole number of control steps.
      self._goal = self._goal_start + self._velocity * self._mjdata.time
      self._show_goal()
    self._goal_velocity_feature[0] = (
      0.0 if person_goal is not None else self._velocity
    )
    sensed_qpos, sensed_qvel = self._sensed_qpos, self._sensed_qvel
    sensed_angle = float(sensed_qpos[-1])
    self._claw_qpos_feature[:] = sensed_qpos[:-1]
    self._claw_qvel_feature[:] = sensed_qvel[:-1]
    self._object_features[:] = (
      math.cos(sensed_angle),
      math.sin(sensed_angle),
      sensed_qvel[-1],
    )
    self._target_error_feature[0] = geometry.wrap_angle(
      self._goal - sensed_angle
    )
    self._distance = abs(
      geometry.wrap_angle(self._goal - float(self._qpos[-1]))
    )

  def _compute_reward_terms(self) -> dict[str, float]:
    distance = self._distance
    pose_diff = np.subtract(self._qpos[:-1], dclaw.RESET_POSE, out=self._diff)
    claw_qvel = self._qvel[:-1]
    fast = np.abs(claw_qvel) >= self.reward_constants.fast_joint_speed
    return {
      'target_dist_cost': -self.reward_constants.target_dist_weight * distance,
      'pose_diff_cost': -geometry.norm(pose_diff),
      'joint_vel_cost': -geometry.norm(claw_qvel[fast]),
      'bonus_small': (
        self.reward_constants.bonus_small
        if distance < self.reward_constants.bonus_small_distance
        else 0.0
      ),
      'bonus_big': (
        self.reward_constants.bonus_big
        if distance < self.reward_constants.bonus_big_distance
        else 0.0
      ),
    }

  def _compute_score(self) -> float:
    return 1.0 - self._distance / math.pi

  def _compute_success(self) -> bool:
    mean_distance = self._episode_mean(self._distance)
    judged = mean_distance if self._success_on_mean else self._distance
    return judged < self._success_threshold


@registry.DCLAW.add(registry.FIXED)
def turn_fixed(**kwargs) -> TurnTask:
  """Turn the valve from 0 to pi."""
  return TurnTask(initial_angle=0.0, goal_angle=np.pi, **kwargs)


@registry.DCLAW.add(registry.RANDOM)
def turn_random(**kwargs) -> TurnTask:
  """Random initial angle near 0 and goal near pi."""
  return TurnTask(
    initial_angle=_RANDOM_INITIAL_ANGLE, goal_angle=_RANDOM_GOAL_ANGLE, **kwargs
  )


@registry.DCLAW.add(registry.RANDOM_DYNAMICS)
def turn_random_dynamics(**kwargs) -> TurnTask:
  """turn_random with randomized dynamics and observation noise."""
  return turn_random(
    dynamics=randomization.DCLAW_VALVE,
    observation_noise=constants.OBSERVATION_NOISE_FRACTION,
    **kwargs,
  )
