"""D'Claw Turn: turn a free valve to a goal angle.

ROBEL's task: docs/robel_reference.md section 2.2.
"""

import math

from dm_control.composer import variation
from dm_control.composer.variation import distributions
import numpy as np

from robel_dm import constants, randomization, registry
from robel_dm.arenas import station
from robel_dm.entities import dclaw
from robel_dm.entities import valve as valve_lib
from robel_dm.tasks import base

_EPISODE_STEPS = 40  # 4 s at 10 Hz.
_SUCCESS_THRESHOLD = 0.1  # |angle error| at the last step, rad.

# Reward weights and thresholds (rad, rad/s).
_TARGET_DIST_WEIGHT = 5.0
_FAST_JOINT_SPEED = 0.5
_BONUS_SMALL, _BONUS_SMALL_DISTANCE = 10.0, 0.25
_BONUS_BIG, _BONUS_BIG_DISTANCE = 50.0, 0.10

# The valve's angle range for observation noise (it has no velocity range, so
# ROBEL adds no velocity noise), rad.
_VALVE_ANGLE_WIDTH = 2 * np.pi

SUCCESS_AT_FINAL_STEP = 'final'
SUCCESS_ON_MEAN_ERROR = 'mean'

# TurnRandom: initial angle and goal offset from pi, rad.
_RANDOM_INITIAL_ANGLE = distributions.Uniform(-np.pi / 3, np.pi / 3)
_RANDOM_GOAL_ANGLE = distributions.Uniform(2 * np.pi / 3, 4 * np.pi / 3)


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
    observation_noise: float = 0.0,
    observation_keys: tuple[str, ...] | None = None,
    action_bounds: str = 'raise',
    use_guide: bool = False,
    interactive: bool = False,
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
      observation_noise: ROBEL's observation-noise fraction.
      observation_keys: the agent's observation; ROBEL's default if None.
      action_bounds: 'raise' or 'clip' for actions outside [-1, 1].
      use_guide: on a robot with ROBEL's guide motor (ID 60): the guide
        points at the goal.
      interactive: on a robot with a guide motor: the guide is released, a
        person turns it, and its angle is the goal.

    Raises:
      ValueError: for an unknown valve or `success_on`.
    """
    if success_on not in (SUCCESS_AT_FINAL_STEP, SUCCESS_ON_MEAN_ERROR):
      raise ValueError(f'success_on must be final or mean: {success_on!r}')
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
    self._use_guide = use_guide
    self._interactive = interactive
    self._velocity = 0.0
    self._goal = 0.0
    super().__init__(
      arena=arena,
      robot=claw,
      control_timestep=constants.CONTROL_TIMESTEP,
      episode_steps=episode_steps,
      extra_sensed_joints=(self._valve.hinge,),
      extra_position_widths=(_VALVE_ANGLE_WIDTH,),
      extra_velocity_widths=(0.0,),
      dynamics=dynamics,
      randomizer_targets=randomization.Targets(
        joints=claw.joints + (self._valve.hinge,),
        actuators=claw.actuators,
        mount=arena.mount,
        colored_geoms=(arena.mount_geom,) + self._valve.valve_geoms,
      ),
      observation_noise=observation_noise,
      observation_keys=observation_keys,
      action_bounds=action_bounds,
    )
    self._claw_qpos_feature = self._features['claw_qpos']
    self._claw_qvel_feature = self._features['claw_qvel']
    self._object_features = self.feature_span('object_x', 'object_qvel')
    self._target_error_feature = self._features['target_error']
    self._diff = np.zeros(len(claw.joints))

  @property
  def valve(self) -> valve_lib.Valve:
    return self._valve

  def hardware_auxiliary_joints(self) -> dict:
    """On hardware the valve angle comes from its motor (ID 50); the guide
    motor (ID 60), with `use_guide` or `interactive`, shows or sets the goal
    (its angle wrapped to [-pi, pi))."""
    motors = {'valve': self._valve.hinge}
    if self._use_guide or self._interactive:
      motors['guide'] = None  # It measures no model joint.
    return motors

  @property
  def initial_angle(self) -> float:
    """The valve angle this episode started from (as drawn), rad."""
    return self._episode_initial_angle

  @property
  def goal(self) -> float:
    """The current goal angle, rad (unwrapped when the goal moves)."""
    return self._goal

  def after_compile(self, physics, random_state) -> None:
    super().after_compile(physics, random_state)
    goal = base.mocap_index(physics, self.arena.goal_body)
    self._goal_quat = physics.data.mocap_quat[goal]  # A view.
    if (self._use_guide or self._interactive) and not hasattr(
      physics, 'auxiliary_angles'
    ):
      raise ValueError(
        'use_guide and interactive need a robot with a guide motor: load the '
        'task with a device_path'
      )

  def _initialize_state(self, physics, random_state) -> None:
    initial = float(
      variation.evaluate(self._initial_angle, random_state=random_state)
    )
    if self._goal_angle is None:
      self._goal_start = initial
    else:
      goal = variation.evaluate(self._goal_angle, random_state=random_state)
      self._goal_start = float(base.wrap_angle(goal))
    self._velocity = float(
      variation.evaluate(self._goal_velocity, random_state=random_state)
    )
    physics.bind(self.robot.joints).qpos = dclaw.RESET_POSE
    physics.bind(self.robot.actuators).ctrl = dclaw.RESET_POSE
    physics.bind(self._valve.hinge).qpos = initial
    self._episode_initial_angle = initial
    self._goal = self._goal_start
    self._show_goal()
    if self._use_guide and not self._interactive:
      physics.auxiliary_goals['guide'] = base.wrap_angle(self._goal)

  def _show_goal(self) -> None:
    half_yaw = self._goal / 2
    self._goal_quat[:] = (math.cos(half_yaw), 0.0, 0.0, math.sin(half_yaw))

  def _compute(self, physics) -> tuple[float, ...]:
    if self._interactive:
      # A person turns the guide; its angle is the goal.
      self._goal = physics.auxiliary_angles.get('guide', self._goal)
      self._show_goal()
    elif self._velocity:
      # The goal moves with time; time is a whole number of control steps.
      self._goal = self._goal_start + self._velocity * self._mjdata.time
      self._show_goal()
      if self._use_guide:
        physics.auxiliary_goals['guide'] = base.wrap_angle(self._goal)
    goal = self._goal
    sensed_qpos, sensed_qvel = self._sensed_qpos, self._sensed_qvel
    sensed_angle = float(sensed_qpos[-1])
    self._claw_qpos_feature[:] = sensed_qpos[:-1]
    self._claw_qvel_feature[:] = sensed_qvel[:-1]
    self._object_features[:] = (
      math.cos(sensed_angle),
      math.sin(sensed_angle),
      sensed_qvel[-1],
    )
    self._target_error_feature[0] = base.wrap_angle(goal - sensed_angle)

    distance = abs(base.wrap_angle(goal - float(self._qpos[-1])))
    claw_qvel = self._qvel[:-1]
    pose_diff = np.subtract(self._qpos[:-1], dclaw.RESET_POSE, out=self._diff)
    fast = np.abs(claw_qvel) >= _FAST_JOINT_SPEED
    small_bonus = _BONUS_SMALL if distance < _BONUS_SMALL_DISTANCE else 0.0
    big_bonus = _BONUS_BIG if distance < _BONUS_BIG_DISTANCE else 0.0
    self._score[...] = 1.0 - distance / math.pi
    mean_distance = self._episode_mean(distance)
    judged = mean_distance if self._success_on_mean else distance
    self._success[...] = judged < self._success_threshold
    return (
      -_TARGET_DIST_WEIGHT * distance,
      -base.norm(pose_diff),
      -base.norm(claw_qvel[fast]),
      small_bonus,
      big_bonus,
    )


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
