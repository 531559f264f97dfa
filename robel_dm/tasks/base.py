"""Machinery shared by every robel_dm task.

A `RobelTask` validates normalized actions and hands them to its robot's
action map (ROBEL's map with the velocity clamp), reads the robot (and
object) joints once per control step, optionally adds ROBEL's observation
noise to that reading, and then, in this order, asks the task for its
observation features, its named reward terms, its score, its success and
whether the episode has failed. Observables only hand out the cached arrays
(composer copies them), so every signal in a timestep comes from the same
physics state.

Observation noise reaches only what the agent observes; reward, score, success
and safety are computed from the true state (see README, fidelity notes).
What a task needs from the robot beyond the physics state (measured
currents, a goal display, tracked targets) it asks of its `RobotIO`.
"""

import collections
from collections.abc import Callable, Mapping
import dataclasses
import math
from typing import Any

from dm_control import composer, mjcf
from dm_control.composer.observation import observable
from dm_env import specs
import numpy as np

from robel_dm import constants, environment, numeric, randomization
from robel_dm import robot_io as robot_io_lib
from robel_dm.entities import servo_robot

# Names of the signal observables every task provides.
SCORE = 'score'
SUCCESS = 'success'
SAFETY = 'safety'
REWARD_TERMS = 'reward_terms'
# The observation `TaskOptions.privileged` appends to the agent's, and the
# option's values: none, everything, the randomized dynamics only.
PRIVILEGED = 'privileged'
PRIVILEGED_CHOICES = (False, True, 'dynamics')

# Order of the counters in the `safety` observation.
SAFETY_FIELDS = ('position', 'velocity', 'current')

# Actions may exceed [-1, 1] by float rounding (e.g. a float32 policy); such
# actions are clipped even when out-of-range actions are rejected.
_ACTION_BOUND_TOLERANCE = 1e-6
ACTION_BOUND_MODES = ('raise', 'clip')
# How an action becomes joint targets: ROBEL's map, or the safe one (see
# `servo_robot.ActionMap`).
ACTION_MAPS = ('robel', 'safe')


def reward_constants(default, given):
  """The reward constants a task runs with: `default` (a frozen dataclass
  of ROBEL's values), replaced whole by an instance of its class, or with
  some fields overridden by a mapping (JSON-friendly, e.g. from
  `--task_kwargs='{"reward": {"joint_vel_weight": 0.2}}'`).

  Raises:
    ValueError: naming unknown fields or values that are not finite numbers.
  """
  if given is None or given is default:
    return default
  if isinstance(given, type(default)):
    _check_reward_values(dataclasses.asdict(given))
    return given
  if not isinstance(given, Mapping):
    raise ValueError(
      f'reward must be a {type(default).__name__} or a mapping of its '
      f'fields, got {given!r}'
    )
  fields = [field.name for field in dataclasses.fields(default)]
  unknown = sorted(set(given) - set(fields))
  if unknown:
    raise ValueError(f'reward: unknown constants {unknown}; known: {fields}')
  _check_reward_values(given)
  return dataclasses.replace(default, **given)


def _check_reward_values(values: Mapping) -> None:
  """Raises ValueError naming a reward constant that is not a finite
  number."""
  for name, value in values.items():
    if not numeric.is_real(value):
      raise ValueError(f'reward.{name} must be a number, got {value!r}')
    if not math.isfinite(value):
      raise ValueError(f'reward.{name} must be finite, got {value}')


def mocap_index(physics, body: mjcf.Element) -> int:
  """Index of a mocap body in `data.mocap_pos` / `data.mocap_quat`."""
  body_id = physics.model.name2id(body.full_identifier, 'body')
  return int(physics.model.body_mocapid[body_id])


@dataclasses.dataclass(frozen=True, kw_only=True, eq=False)
class Scene:
  """What a task builds: its model, its robot and the episode's timing.

  Attributes:
    arena: the root entity; `robot` must already be attached to it.
    robot: the actuated robot; its actuators define the action.
    control_timestep: seconds between actions.
    episode_steps: control steps per episode.
    extra_sensed_joints: non-robot joints read with the robot (e.g. the
      valve), appended after the robot joints.
    extra_position_widths: range widths of those joints for noise, rad.
    extra_velocity_widths: velocity-range widths of those joints, rad/s.
    randomizer_targets: elements dynamics randomization acts on.
    root_joint: the free joint of a free-floating robot, or None.
    privileged_state: what the scene adds to a privileged observation
      (`TaskOptions.privileged`) after the randomized dynamics, e.g. the
      terrain under the D'Kitty; None: nothing.
    privileged_size: the size of what `privileged_state` returns.
    set_randomization_scale: scales what the scene itself randomizes (the
      D'Kitty's terrain) like the task's dynamics, from the next reset
      (`RobelTask.set_randomization_scale`); None: it randomizes nothing.
  """

  arena: composer.Arena
  robot: servo_robot.ServoRobot
  control_timestep: float
  episode_steps: int
  extra_sensed_joints: tuple[mjcf.Element, ...] = ()
  extra_position_widths: tuple[float, ...] = ()
  extra_velocity_widths: tuple[float, ...] = ()
  randomizer_targets: randomization.Targets | None = None
  root_joint: mjcf.Element | None = None
  privileged_state: Callable[[], np.ndarray] | None = None
  privileged_size: int = 0
  set_randomization_scale: Callable[[float], None] | None = None


# Task options that fix what an action means (the valve's shape, the action
# map) or what the agent observes (the privileged observation), with their
# defaults: a policy, demonstrations or networks made under one value do not
# fit a task under another.
INTERFACE_OPTIONS = {
  'valve': 'valve3',
  'action_map': 'robel',
  'privileged': False,
}


def interface_differences(
  made_with: Mapping[str, Any] | None, task_kwargs: Mapping[str, Any] | None
) -> list[tuple[str, Any, Any]]:
  """The `INTERFACE_OPTIONS` whose values differ between the task arguments
  something was made with and a task's: (option, made with, the task's),
  defaults filled in."""
  made_with, task_kwargs = made_with or {}, task_kwargs or {}
  differences = []
  for option, default in INTERFACE_OPTIONS.items():
    theirs = made_with.get(option, default)
    ours = task_kwargs.get(option, default)
    if theirs != ours:
      differences.append((option, theirs, ours))
  return differences


@dataclasses.dataclass(frozen=True, kw_only=True)
class TaskOptions:
  """What a user chooses of any task: the keywords every task factory
  accepts (e.g. `suite.load(..., task_kwargs={'observation_noise': 0.1})`).

  `RobelTask` validates them, as some checks need the task (its features
  and reward constants).

  Attributes:
    dynamics: ranges of per-episode dynamics randomization, or None.
    observation_noise: ROBEL's `sim_observation_noise` fraction; 0 = off.
    observation_keys: the agent's observation, in order; None for ROBEL's
      default keys of the task.
    action_bounds: 'raise' (default) rejects actions outside [-1, 1];
      'clip' clips them as ROBEL did.
    reward: the reward constants (see `reward_constants`); ROBEL's if None.
    action_map: 'robel' (default) maps actions to targets as ROBEL does;
      'safe' keeps the targets inside the safety counters' position bounds
      and moves them no faster than their speed limit (`ActionMap`), so
      that a policy cannot drive a joint into a counted violation.
    privileged: append the `PRIVILEGED` observation to the agent's: True,
      the episode's randomized dynamics (`DynamicsRandomizer.draws`) and
      what the scene adds (the terrain under the D'Kitty); 'dynamics', the
      randomized dynamics only; False (default), nothing. Only a
      simulation knows these: for privileged agents (a ceiling) and
      critics.
  """

  dynamics: randomization.DynamicsRanges | None = None
  observation_noise: float = 0.0
  observation_keys: tuple[str, ...] | None = None
  action_bounds: str = 'raise'
  reward: Any = None
  action_map: str = 'robel'
  privileged: bool | str = False


def _check_options(options: TaskOptions) -> None:
  """Raises ValueError naming the first option of the wrong kind or out of
  range (before any is used)."""
  if options.dynamics is not None and not isinstance(
    options.dynamics, randomization.DynamicsRanges
  ):
    raise ValueError(
      'dynamics must be a randomization.DynamicsRanges or None, got '
      f'{options.dynamics!r}'
    )
  noise = options.observation_noise
  if not numeric.is_finite(noise) or noise < 0:
    raise ValueError(
      f'observation_noise must be a finite number >= 0, got {noise!r}'
    )
  keys = options.observation_keys
  if not (
    keys is None
    or isinstance(keys, str)
    or (
      isinstance(keys, (list, tuple))
      and all(isinstance(key, str) for key in keys)
    )
  ):
    raise ValueError(
      f'observation_keys must be a list of observation names, got {keys!r}'
    )
  if options.action_bounds not in ACTION_BOUND_MODES:
    raise ValueError(
      f'action_bounds must be one of {ACTION_BOUND_MODES}, got '
      f'{options.action_bounds!r}'
    )
  if options.action_map not in ACTION_MAPS:
    raise ValueError(
      f'action_map must be one of {ACTION_MAPS}, got {options.action_map!r}'
    )
  # By identity: 1 == True, and would pass for either.
  privileged = options.privileged
  if not (
    privileged is True or privileged is False or privileged == 'dynamics'
  ):
    raise ValueError(
      f'privileged must be one of {PRIVILEGED_CHOICES}, got {privileged!r}'
    )


class RobelTask(composer.Task):
  """Base class of robel_dm tasks (one level below `composer.Task`).

  Subclasses define the class attributes `FEATURES` (observation name ->
  size, in ROBEL's observation-dict order), `DEFAULT_OBSERVATION_KEYS`
  (ROBEL's default flattened observation, in order) and `REWARD_TERMS` (the
  names of the reward's terms, in order), and implement `_initialize_state`,
  `_compute_features`, `_compute_reward_terms`, `_compute_score` and
  `_compute_success` (and `_compute_failure` if an episode can fail).
  """

  FEATURES: dict[str, int] = {}
  DEFAULT_OBSERVATION_KEYS: tuple[str, ...] = ()
  REWARD_TERMS: tuple[str, ...] = ()
  # ROBEL's reward, score and success constants (a frozen dataclass).
  DEFAULT_REWARD: Any = None

  def __init__(self, scene: Scene, options: TaskOptions):
    """Initializes the task.

    Args:
      scene: what the subclass built (model, robot, timing).
      options: the user's options; the task reads the reward constants
        from `self.reward_constants`.

    Raises:
      ValueError: naming the option, for any of `TaskOptions` of the wrong
        kind or out of range (`_check_options`), unknown or repeated
        observation keys, privileged observations without randomized
        dynamics, or a non-positive episode length.
    """
    _check_options(options)
    self.reward_constants = reward_constants(
      self.DEFAULT_REWARD, options.reward
    )
    action_bounds = options.action_bounds
    observation_noise = options.observation_noise
    episode_steps = scene.episode_steps
    if not numeric.is_integer(episode_steps):
      raise ValueError(f'episode_steps must be an integer: {episode_steps!r}')
    if episode_steps <= 0:
      raise ValueError(f'episode_steps must be positive: {episode_steps}')
    keys = self._checked_keys(options.observation_keys)
    if options.privileged and options.dynamics is None:
      raise ValueError(
        'privileged observations need randomized dynamics (a '
        'RandomDynamics task)'
      )
    robot = scene.robot
    self._arena = scene.arena
    self._robot = robot
    self._root_joint = scene.root_joint
    self._episode_steps = scene.episode_steps
    self._clip_actions = action_bounds == 'clip'
    self._safe_action_map = options.action_map == 'safe'
    self._observation_noise = observation_noise
    self._agent_keys = keys
    self.set_timesteps(
      control_timestep=scene.control_timestep,
      physics_timestep=constants.PHYSICS_TIMESTEP,
    )
    self._sensed_joints = tuple(robot.joints) + tuple(scene.extra_sensed_joints)
    self._extra_position_widths = np.asarray(scene.extra_position_widths, float)
    self._extra_velocity_widths = np.asarray(scene.extra_velocity_widths, float)
    self._randomizer = None
    if options.dynamics is not None:
      self._randomizer = randomization.DynamicsRandomizer(
        options.dynamics, scene.randomizer_targets or randomization.Targets()
      )
    # The scene's share (the terrain) only with privileged=True.
    with_scene = options.privileged is True
    self._scene_privileged_state = (
      scene.privileged_state if with_scene else None
    )
    self._scene_privileged_size = scene.privileged_size if with_scene else 0
    self._scene_randomization_scale = scene.set_randomization_scale

    self._allocate_state(robot, observation_noise)
    self._make_observables(keys)
    if options.privileged:
      self._add_privileged_observable()

  def _checked_keys(self, observation_keys) -> tuple[str, ...]:
    """The agent's observation keys: the given ones or the task's default,
    each a feature of the task, none repeated."""
    if observation_keys is None:
      observation_keys = self.DEFAULT_OBSERVATION_KEYS
    elif isinstance(observation_keys, str):
      observation_keys = (observation_keys,)
    keys = tuple(observation_keys)
    if not keys:
      raise ValueError('observation_keys is empty: name at least one')
    unknown = [key for key in keys if key not in self.FEATURES]
    if unknown:
      raise ValueError(
        f'unknown observation keys {unknown}; this task offers '
        f'{list(self.FEATURES)}'
      )
    if len(set(keys)) != len(keys):
      raise ValueError(f'repeated observation keys: {keys}')
    return keys

  def _allocate_state(self, robot, observation_noise: float) -> None:
    """The buffers a step reuses: joint state, features and signals."""
    num_actions = len(robot.actuators)
    num_sensed = len(self._sensed_joints)
    self._num_robot_joints = len(robot.joints)
    if self._num_robot_joints != num_actions:
      raise ValueError('the robot needs one position actuator per joint')
    self._robot_io: robot_io_lib.RobotIO = robot_io_lib.SIMULATION
    # Reused buffers, to avoid per-step arrays.
    self._scratch = np.zeros(num_actions)
    self._flags = np.zeros(num_actions, dtype=bool)
    # True and sensed (possibly noisy) joint state, robot joints first.
    self._qpos = np.zeros(num_sensed)
    self._qvel = np.zeros(num_sensed)
    # Without noise the agent senses the true state: share the arrays.
    self._sensed_qpos = (
      np.zeros(num_sensed) if observation_noise else self._qpos
    )
    self._sensed_qvel = (
      np.zeros(num_sensed) if observation_noise else self._qvel
    )
    # Views of the robot's share of the true state.
    self._robot_qpos = self._qpos[: self._num_robot_joints]
    self._robot_qvel = self._qvel[: self._num_robot_joints]
    # Motor currents, mA, when the robot measures them (see `RobotIO`);
    # simulation models none, and the current counter stays 0 there.
    self._current = None

    # All features are views of one buffer, in FEATURES order, so that
    # neighbouring features can be written with one assignment.
    self._feature_buffer = np.zeros(sum(self.FEATURES.values()))
    self._feature_offsets = {}
    self._features = {}
    offset = 0
    for name, size in self.FEATURES.items():
      self._feature_offsets[name] = offset
      self._features[name] = self._feature_buffer[offset : offset + size]
      offset += size
    self._last_action = self._features['last_action']
    if self._last_action.size != num_actions:
      raise ValueError(f'last_action must have {num_actions} entries')
    self._reward = 0.0
    # Whether the episode has failed and must end (discount 0).
    self._failed = False
    self._error_sum, self._error_count = 0.0, 0
    self._reward_terms = dict.fromkeys(self.REWARD_TERMS, 0.0)
    self._score = np.zeros(())
    self._success = np.zeros((), dtype=bool)
    self._safety = np.zeros(len(SAFETY_FIELDS), dtype=np.int32)

  def _make_observables(self, keys: tuple[str, ...]) -> None:
    """The features as observables (the agent's enabled), then the score,
    success, safety and (when enabled) reward terms."""
    self._task_observables = collections.OrderedDict()
    ordered = keys + tuple(k for k in self.FEATURES if k not in keys)
    for name in ordered:
      self._add_observable(name, self._features[name], enabled=name in keys)
    self._add_observable(SCORE, self._score)
    self._add_observable(SUCCESS, self._success)
    self._add_observable(SAFETY, self._safety)
    # Built only when enabled: the terms are kept as a dict of floats.
    terms = observable.Generic(
      lambda physics: np.array(list(self._reward_terms.values()))
    )
    terms.enabled = False
    self._task_observables[REWARD_TERMS] = terms

  def _add_privileged_observable(self) -> None:
    """The `PRIVILEGED` observation, last in the agent's."""
    privileged = observable.Generic(lambda physics: self._privileged_state())
    privileged.enabled = True
    self._task_observables[PRIVILEGED] = privileged
    self._agent_keys += (PRIVILEGED,)

  def _privileged_state(self) -> np.ndarray:
    parts = [self._randomizer.draws]
    if self._scene_privileged_state is not None:
      parts.append(self._scene_privileged_state())
    return np.concatenate(parts)

  def feature_span(self, first: str, last: str) -> np.ndarray:
    """A writable view of the features from `first` to `last` (FEATURES
    order), for the code that fills them (the task, or parts it is built
    from)."""
    start = self._feature_offsets[first]
    stop = self._feature_offsets[last] + self.FEATURES[last]
    return self._feature_buffer[start:stop]

  def _add_observable(
    self, name: str, value: np.ndarray, enabled: bool = True
  ) -> None:
    obs = environment.CachedArray(value)
    obs.enabled = enabled
    self._task_observables[name] = obs

  # --- Public API ---------------------------------------------------------

  @property
  def root_entity(self) -> composer.Arena:
    return self._arena

  @property
  def arena(self) -> composer.Arena:
    return self._arena

  @property
  def robot(self) -> composer.Robot:
    return self._robot

  @property
  def root_joint(self) -> mjcf.Element | None:
    """The free joint of a free-floating robot (D'Kitty), else None."""
    return self._root_joint

  @property
  def task_observables(self) -> collections.OrderedDict:
    return self._task_observables

  @property
  def action_map(self) -> str:
    """How actions become joint targets: 'robel' or 'safe'."""
    return ACTION_MAPS[1] if self._safe_action_map else ACTION_MAPS[0]

  @property
  def agent_observation_keys(self) -> tuple[str, ...]:
    """Names of the observations the agent sees, in flattening order."""
    return self._agent_keys

  @property
  def agent_observation_size(self) -> int:
    """The size of the agent's flattened observation (known before the
    model compiles)."""
    size = sum(self.FEATURES.get(key, 0) for key in self._agent_keys)
    if PRIVILEGED in self._agent_keys:
      size += self._randomizer.draw_count + self._scene_privileged_size
    return size

  @property
  def episode_steps(self) -> int:
    return self._episode_steps

  @property
  def time_limit(self) -> float:
    """Episode length in seconds: `episode_steps` control steps."""
    return self._episode_steps * self.control_timestep

  @property
  def settle_substeps(self) -> int:
    """Physics steps a reset runs to let the robot settle (0: none)."""
    return 0

  @property
  def dynamics(self) -> randomization.DynamicsRanges | None:
    return self._randomizer.ranges if self._randomizer else None

  @property
  def dynamics_draws(self) -> dict[str, np.ndarray]:
    """The episode's randomized physics, each quantity's draws scaled to
    [-1, 1] over its range (`DynamicsRandomizer.draws`, by `DynamicsRanges`
    field); empty when the task randomizes no physics."""
    if self._randomizer is None:
      return {}
    return self._randomizer.draws_by_quantity()

  def set_randomization_scale(self, scale: float) -> None:
    """Moves the episodes' randomized physics (and the D'Kitty's terrain)
    to `scale` of their distance from the nominal robot, from the next
    reset on: 1 is the task as defined, 0 the nominal robot on flat ground
    (a curriculum over the randomization; noise is left as it is). The
    random draws, and so the episodes' other randomness, do not change.

    Raises:
      ValueError: if `scale` is outside [0, 1] or the task randomizes no
        physics.
    """
    if self._randomizer is None:
      raise ValueError(f'{type(self).__name__} randomizes no physics')
    self._randomizer.scale = scale
    if self._scene_randomization_scale is not None:
      self._scene_randomization_scale(self._randomizer.scale)

  @property
  def randomization_scale(self) -> float | None:
    """The scale `set_randomization_scale` set (1 unless set); None if the
    task randomizes no physics."""
    return None if self._randomizer is None else self._randomizer.scale

  @property
  def observation_noise(self) -> float:
    return self._observation_noise

  @property
  def reward_terms(self) -> dict[str, float]:
    """The reward's named terms at the last step; the reward is their sum."""
    return dict(self._reward_terms)

  @property
  def robot_io(self) -> robot_io_lib.RobotIO:
    """What the task asks of the robot beyond the physics state."""
    return self._robot_io

  def use_robot_io(self, robot_io: robot_io_lib.RobotIO) -> None:
    """Runs the task on a robot with its own inputs and outputs (a real
    robot's); call before the environment compiles the model.

    Raises:
      TypeError: if `robot_io` does not implement `RobotIO`.
    """
    if not isinstance(robot_io, robot_io_lib.RobotIO):
      raise TypeError(f'{robot_io!r} does not implement RobotIO')
    self._robot_io = robot_io

  def flatten_observation(self, observation) -> np.ndarray:
    """Concatenates the agent's observations in `agent_observation_keys` order.

    Args:
      observation: a timestep's observation dict.

    Returns:
      A float64 vector (ROBEL's flattened observation).
    """
    return np.concatenate(
      [np.ravel(observation[key]) for key in self._agent_keys]
    )

  def auxiliary_joints(self) -> dict[str, mjcf.Element]:
    """Non-robot joints the task observes: name -> model joint.

    On a real robot each is measured by the robot configuration's auxiliary
    motor of that name (e.g. the D'Claw's 'valve' encoder).
    """
    return {}

  @property
  def goal_is_an_angle(self) -> bool:
    """Whether the task's goal is one angle, which a guide motor can show
    (`RobotIO.show_goal`) or a person can set (`goal_from_person`)."""
    return False

  def reference_action(self, physics) -> np.ndarray:
    """The action of the task's scripted reference controller.

    Raises:
      NotImplementedError: if the task has no scripted controller.
    """
    del physics
    raise NotImplementedError(
      f'{type(self).__name__} has no scripted reference controller'
    )

  def checked_pose(self, physics, name: str, pose) -> np.ndarray:
    """`pose` (an option's value this episode) as joint angles, rad.

    Raises:
      ValueError: naming `name`, for a pose of the wrong size or a joint
        outside its action range (before the robot moves).
    """
    pose = np.asarray(pose, dtype=float)
    low, high = physics.bind(self._robot.actuators).ctrlrange.T
    if pose.shape != low.shape:
      raise ValueError(
        f'{name} needs {low.size} joint angles, got shape {pose.shape}'
      )
    outside = np.flatnonzero(~((pose >= low) & (pose <= high)))
    if outside.size:
      i = outside[0]
      raise ValueError(
        f'{name}: joint {self._robot.joints[i].name} at {pose[i]} rad lies '
        f'outside its action range [{low[i]:+.3f}, {high[i]:+.3f}]'
      )
    return pose

  def normalize_joint_targets(self, targets: np.ndarray) -> np.ndarray:
    """Maps joint angles (rad) to actions in [-1, 1]; inverse of the map."""
    return self._action_map.normalize(targets)

  def action_spec(self, physics) -> specs.BoundedArray:
    del physics
    names = [actuator.name for actuator in self._robot.actuators]
    return specs.BoundedArray(
      shape=(len(names),),
      dtype=np.float64,
      minimum=-1.0,
      maximum=1.0,
      name='\t'.join(names),
    )

  # --- composer hooks ------------------------------------------------------

  def after_compile(self, physics, random_state) -> None:
    del random_state
    sensed = physics.bind(self._sensed_joints)
    self._qpos_index = servo_robot.address_index(sensed.qposadr)
    self._qvel_index = servo_robot.address_index(sensed.dofadr)
    self._action_map = self._robot.action_map(
      physics, self.control_timestep, safe=self._safe_action_map
    )
    self._safe_low, self._safe_high = self._robot.safe_bounds(physics)
    limits = self._robot.safety_limits
    self._max_safe_speed = limits.max_speed
    self._max_safe_current = limits.max_current
    # The hot path reads these views of MjData directly.
    self._data_qpos = physics.data.qpos
    self._data_qvel = physics.data.qvel
    self._mjdata = physics.data.ptr  # The raw mujoco.MjData (fast `time`).
    # ROBEL's noise half-widths per sensed joint: positions over the action
    # range (given widths for extra joints), velocities over +-max speed.
    speed = self._robot.max_joint_speed
    action_map = self._action_map
    position_widths = np.concatenate(
      [action_map.high - action_map.low, self._extra_position_widths]
    )
    velocity_widths = np.concatenate(
      [np.full(self._num_robot_joints, 2 * speed), self._extra_velocity_widths]
    )
    self._noise_halfwidths = np.stack(
      [
        randomization.noise_halfwidths(
          position_widths, self._observation_noise
        ),
        randomization.noise_halfwidths(
          velocity_widths, self._observation_noise
        ),
      ]
    )
    if self._randomizer is not None:
      self._randomizer.after_compile(physics)
    self._current = self._robot_io.motor_currents

  def initialize_episode(self, physics, random_state) -> None:
    if self._randomizer is not None:
      self._randomizer.apply(physics, random_state)
    self._last_action[:] = 0.0
    self._error_sum, self._error_count = 0.0, 0
    self._failed = False
    self._initialize_state(physics, random_state)
    # A real robot must be moved to the state just set, and the first
    # observation must come from where it actually is.
    self._robot_io.realize_initial_state()
    self._update(physics, random_state)

  def before_step(self, physics, action, random_state) -> None:
    del physics, random_state
    self._last_action[:] = self.validated_action(action)
    self._action_map.apply(self._last_action)

  def after_step(self, physics, random_state) -> None:
    self._update(physics, random_state)

  def get_reward(self, physics) -> float:
    del physics
    return self._reward

  def should_terminate_episode(self, physics) -> bool:
    del physics
    return self._failed

  def get_discount(self, physics) -> float:
    # A failure (e.g. a fall) is terminal; a time limit is not.
    del physics
    return 0.0 if self._failed else 1.0

  # --- Subclass interface --------------------------------------------------

  def _initialize_state(self, physics, random_state) -> None:
    """Sets the episode's initial state and goal (inside reset_context)."""
    raise NotImplementedError

  def _compute_features(self, physics) -> None:
    """Fills the observation features, and keeps what the reward, score and
    success need, from `_qpos`/`_qvel` (true state) and
    `_sensed_qpos`/`_sensed_qvel` (what the agent observes). Called once per
    control step and at reset, before the methods below."""
    raise NotImplementedError

  def _compute_reward_terms(self) -> dict[str, float]:
    """The reward's terms, named as in `REWARD_TERMS` and in that order."""
    raise NotImplementedError

  def _compute_score(self) -> float:
    """ROBEL's points for this step."""
    raise NotImplementedError

  def _compute_success(self) -> bool:
    """ROBEL's success evaluator for the episode so far."""
    raise NotImplementedError

  def _compute_failure(self) -> bool:
    """Whether the episode has failed and must end (e.g. a fall)."""
    return False

  # --- Helpers -------------------------------------------------------------

  def _update(self, physics, random_state) -> None:
    self._qpos[:] = self._data_qpos[self._qpos_index]
    self._qvel[:] = self._data_qvel[self._qvel_index]
    if self._observation_noise:
      noise = random_state.uniform(-1.0, 1.0, self._noise_halfwidths.shape)
      noise *= self._noise_halfwidths
      np.add(self._qpos, noise[0], out=self._sensed_qpos)
      np.add(self._qvel, noise[1], out=self._sensed_qvel)
    self._compute_features(physics)
    self._reward_terms = terms = self._compute_reward_terms()
    self._reward = sum(terms.values())
    self._score[...] = self._compute_score()
    self._success[...] = self._compute_success()
    self._failed = self._compute_failure()
    self._update_safety()

  def _episode_mean(self, error: float) -> float:
    """Adds this step's error to the episode's and returns their mean.

    ROBEL's success evaluators for Pose and Screw judge the mean tracking
    error of the whole episode, reset state included.
    """
    self._error_sum += error
    self._error_count += 1
    return self._error_sum / self._error_count

  def _update_safety(self) -> None:
    qpos, flags, count = self._robot_qpos, self._flags, np.count_nonzero
    near_limits = count(np.less(qpos, self._safe_low, out=flags))
    near_limits += count(np.greater(qpos, self._safe_high, out=flags))
    self._safety[0] = near_limits
    speed = np.abs(self._robot_qvel, out=self._scratch)
    self._safety[1] = count(np.greater(speed, self._max_safe_speed, out=flags))
    if self._current is not None:
      over = np.abs(self._current) > self._max_safe_current
      self._safety[2] = count(over)

  def validated_action(self, action) -> np.ndarray:
    """`action` as the task takes it (float64, in range).

    Raises:
      ValueError: naming what is wrong with it (dtype, shape, a value out
        of [-1, 1] or not finite), as `step` would.
    """
    action = np.asarray(action)
    if action.dtype != np.float64:
      if action.dtype.kind not in 'biuf':  # Complex, strings, objects.
        raise ValueError(
          f'action must be real numbers, got dtype {action.dtype}: '
          f'{action.tolist()}'
        )
      action = action.astype(np.float64)
    expected = self._last_action.shape
    if action.shape != expected:
      raise ValueError(
        f'action has shape {action.shape}, expected {expected} '
        '(one normalized joint target in [-1, 1] per actuator)'
      )
    # One comparison covers the common case; NaN fails it too.
    in_bounds = np.less_equal(
      np.abs(action, out=self._scratch), 1.0, out=self._flags
    )
    if np.count_nonzero(in_bounds) == in_bounds.size:
      return action
    finite = np.isfinite(action)
    if not finite.all():
      bad = np.flatnonzero(~finite).tolist()
      raise ValueError(f'action has non-finite entries at indices {bad}')
    outside = np.abs(action) > 1.0 + _ACTION_BOUND_TOLERANCE
    if outside.any() and not self._clip_actions:
      bad = np.flatnonzero(outside).tolist()
      raise ValueError(
        f'action outside [-1, 1] at indices {bad}: {action[bad].tolist()} '
        "(pass task_kwargs={'action_bounds': 'clip'} to clip instead)"
      )
    return np.clip(action, -1.0, 1.0)
