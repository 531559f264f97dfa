"""A dm_env wrapper that records every timestep of a robel_dm environment."""

import json
import logging
import pathlib
import time
from typing import Any

import dm_env
import numpy as np

from robel_dm import provenance
from robel_dm.recording import format as format_lib
from robel_dm.tasks import base, dkitty_walk


def _value(value):
  """A timestep value as a Parquet-friendly Python value."""
  array = np.asarray(value)
  if array.ndim == 0:
    return array.item()
  return array.astype(np.float64).ravel().tolist()


# The units of the columns (docs/recording.md has the table), each checked
# against the code that makes the value: '' unitless, None unknown.
_UNITS = {
  'episode_index': '',
  'frame_index': '',
  'timestamp': 's',  # physics.data.time (a robot's: control ticks x period)
  'wall_time': 's',  # time.time()
  'step_type': '',
  'action': '',  # Normalized, [-1, 1].
  'joint_targets': 'rad',  # The position actuators' ctrl.
  'next.reward': '',
  'discount': '',
  'next.done': '',
  # hardware.robot.HardwareRobot: calibrated joint units; currents as the
  # client reads them (mA, the motor's sign); temperature in 1 C steps;
  # input voltage in 0.1 V steps; the timestamps are time.monotonic().
  'motor.position': 'rad',
  'motor.velocity': 'rad/s',
  'motor.current': 'mA',
  'motor.timestamp': 's',
  'motor.temperature': 'degC',
  'motor.voltage': 'V',
  'motor.hardware_error': '',  # Hardware Error Status bits.
  'motor.health_timestamp': 's',
}
# The observations' units, by key (the tasks' `_compute_features`).
_OBSERVATION_UNITS = {
  'qpos': 'rad',
  'qvel': 'rad/s',
  'qpos_error': 'rad',
  'claw_qpos': 'rad',
  'claw_qvel': 'rad/s',
  'object_x': '',  # cos of the valve angle.
  'object_y': '',  # sin of the valve angle.
  'object_qvel': 'rad/s',
  'last_action': '',
  'target_error': 'rad',  # D'Claw: the wrapped valve angle error.
  'goal_velocity': 'rad/s',
  'upright': '',  # The torso's z axis' z component.
  'root_pos': 'm',
  'root_euler': 'rad',
  'root_vel': 'm/s',
  'root_angular_vel': 'rad/s',  # Rates of root_euler.
  'kitty_qpos': 'rad',
  'kitty_qvel': 'rad/s',
  'pose_error': 'rad',
  'current_facing': '',  # The torso's y axis on the floor.
  'desired_facing': '',  # Unit vector.
  'angle_error': 'rad',
  'heading': '',  # A cosine.
  'target_pos': 'm',
  base.SCORE: '',
  base.SUCCESS: '',
  base.SAFETY: '',  # Counts.
}
# Keys whose unit differs on some tasks: task class -> key -> unit.
_TASK_UNITS = {dkitty_walk.WalkTask: {'target_error': 'm'}}
# Vector columns with one entry per joint of the robot, in action order.
_JOINT_COLUMNS = frozenset(
  ('action', 'joint_targets')
  + tuple(
    f'observation.{key}'
    for key in (
      'qpos',
      'qvel',
      'qpos_error',
      'claw_qpos',
      'claw_qvel',
      'kitty_qpos',
      'kitty_qvel',
      'pose_error',
      'last_action',
    )
  )  # fmt: skip
)
_XYZ, _XY = ('x', 'y', 'z'), ('x', 'y')
# Observations whose entries are axes (world frame; root_euler's xyz
# angles and their rates).
_AXES = {
  'root_pos': _XYZ,
  'root_euler': _XYZ,
  'root_vel': _XYZ,
  'root_angular_vel': _XYZ,
  'target_pos': _XY,
  'target_error': _XY,
  'current_facing': _XY,
  'desired_facing': _XY,
  base.SAFETY: base.SAFETY_FIELDS,
}


def _names(column: str, size: int, joints: tuple, motors: tuple):
  """The dimension names of a vector column of `size` entries (None if
  unknown)."""
  key = column.removeprefix('observation.')
  for names in (
    joints if column in _JOINT_COLUMNS else None,
    motors if column.startswith('motor.') else None,
    _AXES.get(key) if key != column else None,
  ):
    if names is not None and len(names) == size:
      return list(names)
  return [key] if size == 1 and key != column else None


def column_description(env, row: dict[str, Any], session: dict[str, Any]):
  """The description of the columns of `row` (see
  `reader.describe_columns`): computed once per episode, from its first
  row."""
  task = env.task
  joints = tuple(joint.name for joint in task.robot.joints)
  robot = getattr(env, 'robot', None)  # A HardwareEnvironment's motors.
  motors = tuple(robot.motor_ids) if robot is not None else ()
  units = dict(_OBSERVATION_UNITS)
  for cls in reversed(type(task).__mro__):
    units.update(_TASK_UNITS.get(cls, {}))
  columns = {}
  for column, value in row.items():
    if column.startswith('observation.'):
      unit = units.get(column.removeprefix('observation.'))
    elif column.startswith('reward_terms.'):
      unit = ''
    else:
      unit = _UNITS.get(column)
    description = {'unit': unit}
    if isinstance(value, list):
      description['shape'] = [len(value)]
      description['names'] = _names(column, len(value), joints, motors)
    else:
      description['shape'] = []
    columns[column] = description
  return {
    **{key: session.get(key) for key in ('domain', 'task', 'task_kwargs')},
    'task_class': type(task).__name__,
    'fps': 1 / env.control_timestep(),
    'columns': columns,
  }


# What binds a recording directory to one task: the session metadata keys
# compared when both the recorded and the new session name them.
_TASK_KEYS = ('domain', 'task', 'task_kwargs')


def _describe(info: dict[str, Any], keys: bool) -> str:
  session = info.get('session') or {}
  name = '/'.join(str(session[k]) for k in ('domain', 'task') if k in session)
  if session.get('task_kwargs'):
    name += f' {json.dumps(session["task_kwargs"], sort_keys=True)}'
  name = name or 'an unnamed task'
  if keys:
    name += f' (observations {",".join(info.get("observation_keys") or [])})'
  return name


def _check_same_task(directory: pathlib.Path, info: dict[str, Any]) -> None:
  """Raises RecordingError if `directory` holds a recording whose task or
  observation keys differ from `info`'s."""
  path = directory / format_lib.INFO
  if not path.is_file():
    return
  try:
    old = json.loads(path.read_text())
    new = json.loads(json.dumps(info))  # Tuples as lists, as recorded.
  except (OSError, TypeError, ValueError) as error:
    raise format_lib.RecordingError(
      f'cannot check {path} before recording into {directory}: {error}'
    ) from error
  if not isinstance(old, dict) or old.get('format') != format_lib.FORMAT:
    raise format_lib.RecordingError(f'{path} is not a robel_dm recording')
  old_session, new_session = old.get('session') or {}, new['session']
  other_task = any(
    key in old_session
    and key in new_session
    and old_session[key] != new_session[key]
    for key in _TASK_KEYS
  )
  keys = new['observation_keys']
  other_keys = old.get('observation_keys', keys) != keys
  if other_task or other_keys:
    raise format_lib.RecordingError(
      f'{directory} holds a recording of {_describe(old, other_keys)}, not '
      f'{_describe(new, other_keys)}: record into another directory'
    )


class Recorder(dm_env.Environment):
  """Records `env`'s timesteps into a recording directory as they happen.

  Everything else (specs, `physics`, `task`, attributes) passes through to
  the wrapped environment. `close()` closes the environment (releasing a
  robot) and then finishes the open episode (marked incomplete if it had
  not ended).
  """

  def __init__(
    self,
    env: dm_env.Environment,
    directory: str | pathlib.Path,
    *,
    metadata: dict[str, Any] | None = None,
  ):
    """Checks the directory and starts the recording.

    Args:
      env: a robel_dm environment (simulated or on a robot).
      directory: the recording directory (created; episodes are added
        after any already there).
      metadata: what every episode's line records besides the task (e.g.
        domain, task, task_kwargs, seed, policy, device_path).

    Raises:
      RecordingError: if the directory is not writable, the disk is full,
        another process records into it, or it holds a recording of
        another task or observation keys (the
        session's domain, task or task_kwargs, where both name them;
        checked again once the directory's lock is held); raised before
        the robot moves and before any episode is written.
    """
    self._env = env
    self._action_size = env.action_spec().shape[0]
    self._directory = pathlib.Path(directory)
    self._metadata = dict(metadata or {})
    config = getattr(env, 'robot_config', None)  # A robot's motors.
    self._robot_config = {} if config is None else config.describe()
    info = {
      'format': format_lib.FORMAT,
      'version': format_lib.VERSION,
      'fps': 1 / env.control_timestep(),
      'provenance': provenance.describe(),
      'session': self._metadata,
      'robot': self._robot_config,
      'observation_keys': list(env.task.agent_observation_keys),
    }
    _check_same_task(self._directory, info)  # Before anything is written.
    format_lib.prepare(self._directory)
    self._lock = format_lib.lock(self._directory)
    try:
      # Again under the lock, which decides: a recorder of another task may
      # have started, written its info.json and closed since the check.
      _check_same_task(self._directory, info)
      format_lib.write_atomically(
        self._directory / format_lib.INFO, json.dumps(info, indent=1)
      )
    except format_lib.RecordingError:
      self._lock.close()
      raise
    except (OSError, TypeError, ValueError) as error:
      self._lock.close()
      raise format_lib.RecordingError(
        f'cannot write {self._directory}: {error}'
      ) from error
    self._writer: format_lib.EpisodeWriter | None = None
    # What ended the episode under way, if a step raised.
    self._ended_by: str | None = None
    self._frame = 0
    self._start_wall = 0.0

  def __getattr__(self, name):
    return getattr(self._env, name)

  def annotate(self, **values: Any) -> None:
    """Records `values` in the line of the episode under way and of every
    later one (until annotated again), e.g. `purpose='evaluation'`."""
    self._metadata.update(values)

  # --- dm_env.Environment ----------------------------------------------------

  def reset(self) -> dm_env.TimeStep:
    self._finish(complete=False)
    timestep = self._env.reset()
    self._start_episode(timestep)
    return timestep

  def step(self, action) -> dm_env.TimeStep:
    if self._ended_by is not None:  # Stepping on after a fault.
      self._finish(complete=False)
    try:
      timestep = self._env.step(action)
    except BaseException as error:
      # A fault (or Ctrl-C) ends the episode, and its metadata says why.
      # The file is finished at close() (or the next reset, or step), after
      # the caller has released the robot: writing it takes seconds.
      self._ended_by = f'{type(error).__name__}: {error}'
      raise
    if timestep.first():  # dm_env resets on a step after the last one.
      self._finish(complete=False)
      self._start_episode(timestep)
      return timestep
    if self._writer is not None:
      self._record(timestep, action)
      if timestep.last():
        self._finish(complete=True)
    return timestep

  def _start_episode(self, timestep: dm_env.TimeStep) -> None:
    index = format_lib.next_index(self._directory)
    self._frame = 0
    self._start_wall = time.time()
    row = self._row(index, timestep, action=None)
    self._writer = format_lib.EpisodeWriter(
      self._directory,
      index,
      self._episode_metadata(index),
      column_description(self._env, row, self._metadata),
    )
    self._writer.add(row)
    self._frame += 1

  def observation_spec(self):
    return self._env.observation_spec()

  def action_spec(self):
    return self._env.action_spec()

  def reward_spec(self):
    return self._env.reward_spec()

  def discount_spec(self):
    return self._env.discount_spec()

  def close(self) -> None:
    """Closes the environment (releasing a robot) first, then finishes the
    episode under way."""
    ended_by = self._ended_by
    try:
      self._env.close()
    finally:
      try:
        self._finish(complete=False)
      except format_lib.RecordingError as error:
        if ended_by is None:
          raise
        # The fault that ended the episode is the error to report: this
        # one must not replace it while it propagates.
        logging.error('%s (the episode ended by %s)', error, ended_by)
      finally:
        self._lock.close()

  # --- Recording -------------------------------------------------------------

  def _record(self, timestep: dm_env.TimeStep, action) -> None:
    self._writer.add(self._row(self._writer.index, timestep, action))
    self._frame += 1

  def _row(self, index: int, timestep: dm_env.TimeStep, action) -> dict:
    """The row of a timestep of episode `index`."""
    env = self._env
    row = {
      'episode_index': index,
      'frame_index': self._frame,
      'timestamp': float(env.physics.data.time),
      'wall_time': time.time(),
      'step_type': int(timestep.step_type),
      'action': (
        [float('nan')] * self._action_size if action is None else _value(action)
      ),
      'joint_targets': _value(env.physics.bind(env.task.robot.actuators).ctrl),
      'next.reward': float('nan')
      if timestep.reward is None
      else float(timestep.reward),
      'discount': float('nan')
      if timestep.discount is None
      else float(timestep.discount),
      'next.done': bool(timestep.last()),
    }
    for key, value in timestep.observation.items():
      row[f'observation.{key}'] = _value(value)
    for name, value in env.task.reward_terms.items():
      row[f'reward_terms.{name}'] = float(value)
    robot = getattr(env, 'robot', None)  # A HardwareEnvironment's motors.
    if robot is not None:
      row['motor.position'] = robot.positions.tolist()
      row['motor.velocity'] = robot.velocities.tolist()
      row['motor.current'] = robot.currents.tolist()
      row['motor.timestamp'] = time.monotonic()
      row['motor.temperature'] = robot.temperatures.tolist()
      row['motor.voltage'] = robot.voltages.tolist()
      row['motor.hardware_error'] = robot.hardware_errors.tolist()
      row['motor.health_timestamp'] = robot.health_time
    return row

  def _episode_metadata(self, index: int) -> dict[str, Any]:
    """What the episode's line says besides its ending (also stored in its
    stream at the start, for a partial episode)."""
    metadata = {
      **self._metadata,
      'episode_index': index,
      'start_time': self._start_wall,
    }
    if self._robot_config:
      metadata['robot'] = self._robot_config
    return metadata

  def _finish(self, complete: bool) -> None:
    writer, self._writer = self._writer, None
    error, self._ended_by = self._ended_by, None
    if writer is None:
      return
    metadata = {
      **self._episode_metadata(writer.index),
      'complete': complete,
    }
    if error is not None:
      metadata['error'] = error
    writer.finish(metadata)
