"""Loads robel_dm tasks as dm_env environments.

    from robel_dm import suite
    env = suite.load('dclaw', 'turn_fixed', seed=0)

`suite.load` is the only place that wraps tasks in an environment, so the
performance-critical settings (compile the MJCF once, batch substeps, strip
singleton observation dimensions) are the same for every task.
"""

from collections.abc import Callable, Mapping
import difflib
import math
import os
from typing import Any

from robel_dm import calibration as calibration_lib
from robel_dm import constants, registry
from robel_dm.environment import Environment

# Installs the exit-signal handlers that release a robot's motors, from the
# thread importing the suite (the main thread, as a rule): only the main
# thread can install them, and a robot may be driven from another thread.
from robel_dm.hardware import shutdown  # noqa: F401, I001
from robel_dm.hardware.options import RobotOptions

# Importing a task family's module registers its tasks (hence F401);
# `base` and `excitation` are used below.
from robel_dm.tasks import (  # noqa: F401
  base,
  dclaw_pose,
  dclaw_screw,
  dclaw_turn,
  dkitty_orient,
  dkitty_stand,
  dkitty_walk,
  excitation,
)

# A calibration: a `calibration.Calibration` or the path of its file.
Dynamics = calibration_lib.Calibration | str | os.PathLike

# Half a physics step, s: absorbs rounding in the accumulated physics time.
_TIME_LIMIT_MARGIN = constants.PHYSICS_TIMESTEP / 2


def _tagged(tag: str) -> tuple[tuple[str, str], ...]:
  return tuple(
    (domain, name)
    for domain, tasks in registry.DOMAINS.items()
    for name in tasks
    if name in tasks.tagged(tag)
  )


ALL_TASKS = tuple(
  (domain, name) for domain, tasks in registry.DOMAINS.items() for name in tasks
)
TASKS_BY_DOMAIN = {
  domain: tuple(tasks) for domain, tasks in registry.DOMAINS.items()
}
FIXED = _tagged(registry.FIXED)
RANDOM = _tagged(registry.RANDOM)
RANDOM_DYNAMICS = _tagged(registry.RANDOM_DYNAMICS)
# dm_control.suite's name for the tasks a benchmark reports: here every
# task is one (ROBEL's 18, each in the baseline table).
BENCHMARKING = ALL_TASKS


def _unknown(kind: str, name: str, known) -> ValueError:
  known = sorted(known)
  close = difflib.get_close_matches(name, known, n=1)
  hint = f' Did you mean {close[0]!r}?' if close else ''
  return ValueError(f'unknown {kind} {name!r}; expected one of {known}.{hint}')


def _checked_task(domain: str, task: str, task_kwargs) -> dict:
  """The domain's tasks, once `task` is one of them and `task_kwargs` has
  no dm_control-style random state; a ValueError naming the fix if not."""
  if domain not in registry.DOMAINS:
    raise _unknown('domain', domain, registry.DOMAINS)
  tasks = registry.DOMAINS[domain]
  if task not in tasks:
    owners = [d for d, ts in registry.DOMAINS.items() if task in ts]
    if owners:
      raise ValueError(
        f'unknown {domain} task {task!r}: that task belongs to {owners[0]} '
        f'(suite.load({owners[0]!r}, {task!r}))'
      )
    raise _unknown(f'{domain} task', task, tasks)
  if task_kwargs is not None and not isinstance(task_kwargs, Mapping):
    raise ValueError(
      f'task_kwargs must be a mapping of option names, got {task_kwargs!r}'
    )
  if 'random' in (task_kwargs or {}):
    raise ValueError(
      "task_kwargs={'random': ...}: robel_dm tasks take no random state; "
      'pass seed= to suite.load (dm_control.suite passes it as '
      "task_kwargs['random'])"
    )
  return tasks


def load(
  domain: str,
  task: str,
  task_kwargs: dict[str, Any] | None = None,
  environment_kwargs: dict[str, Any] | None = None,
  *,
  seed: int | None = None,
  time_limit: float | None = None,
  robot: RobotOptions | None = None,
  dynamics: Dynamics | None = None,
) -> Environment:
  """Builds a task's environment.

  Args:
    domain: 'dclaw' or 'dkitty'.
    task: a task of the domain, e.g. 'turn_fixed' (see `TASKS_BY_DOMAIN`).
    seed: seed of the environment's random state (initial states, goals,
      dynamics and observation noise); None draws one from the OS.
    time_limit: episode length in seconds; defaults to ROBEL's. The episode
      ends at the first control step at or after this time.
    task_kwargs: keyword arguments of the task, e.g. `{'valve': 'valve4'}`.
    environment_kwargs: extra `composer.Environment` arguments.
    robot: run on a robot: a `RobotOptions`, e.g.
      `RobotOptions('/dev/ttyUSB0', reset='move')` (its bus's device, or
      'virtual' for an in-process virtual bus driven by a simulation; its
      configuration, reset, guide motor and tracker). None (default)
      simulates.
    dynamics: a calibration (file path or `calibration.Calibration`, e.g.
      from `robel-sysid fit`) of the simulated robot's joint
      dynamics and control delay. On `RobotOptions('virtual')` it
      calibrates the simulation behind the virtual bus; a real robot has
      its own.

  Returns:
    A `dm_env.Environment` (a `composer.Environment`).

  Raises:
    ValueError: for an unknown domain, task or task argument, a `robot`
      that is not a `RobotOptions`, or privileged observations on a robot.
    calibration.CalibrationError: for a malformed calibration or one of
      another robot.
  """
  tasks = _checked_task(domain, task, task_kwargs)
  if robot is not None and (task_kwargs or {}).get('privileged'):
    raise ValueError(
      'privileged observations are what only a simulation knows: a robot '
      'gives none (a policy that reads them cannot run on a robot)'
    )

  def make_task() -> base.RobelTask:
    try:
      return tasks[task](**(task_kwargs or {}))
    except TypeError as error:
      # Only a wrong argument is the caller's mistake; re-raise anything else.
      if 'keyword argument' not in str(error):
        raise
      raise ValueError(
        f'bad task_kwargs for {domain}/{task}: {error}'
      ) from error

  return _environment(
    domain,
    make_task,
    seed=seed,
    time_limit=time_limit,
    environment_kwargs=environment_kwargs,
    robot=_robot_options(robot),
    dynamics=dynamics,
  )


def _robot_options(robot) -> RobotOptions | None:
  """`robot`, checked: a `RobotOptions` or None (simulate)."""
  if robot is not None and not isinstance(robot, RobotOptions):
    raise ValueError(
      f'robot must be a suite.RobotOptions (e.g. '
      f"suite.RobotOptions('/dev/ttyUSB0')) or None, got {robot!r}"
    )
  return robot


def load_excitation(
  domain: str,
  duration: float,
  *,
  seed: int | None = None,
  robot: RobotOptions | None = None,
  dynamics: Dynamics | None = None,
) -> Environment:
  """The joint-excitation environment of system identification.

  The robot alone (the D'Claw in its pose station, the D'Kitty on a stand),
  following ROBEL-normalized joint targets at 50 Hz; see
  `robel_dm.tasks.excitation` and docs/sysid.md.

  Args:
    domain: 'dclaw' or 'dkitty'.
    duration: episode length, s.
    seed: the environment's seed.
    robot: a robot to run on, as for `load`; None simulates.
    dynamics: a calibration of the simulated robot, as for `load`.

  Returns:
    A `dm_env.Environment`.
  """
  if domain not in excitation.DOMAINS:
    raise _unknown('domain', domain, excitation.DOMAINS)
  return _environment(
    domain,
    lambda: excitation.JointExcitation(domain, duration),
    seed=seed,
    time_limit=None,
    environment_kwargs=None,
    robot=_robot_options(robot),
    dynamics=dynamics,
  )


def _environment(
  domain: str,
  make_task: Callable[[], base.RobelTask],
  *,
  seed,
  time_limit,
  environment_kwargs,
  robot: RobotOptions | None,
  dynamics,
) -> Environment:
  """Wraps a new task in a simulated or hardware environment."""
  task_instance = make_task()
  if time_limit is None:
    time_limit = task_instance.time_limit
  elif not time_limit > 0:  # Also NaN.
    raise ValueError(
      f'time_limit must be a positive number of seconds (inf: no limit), '
      f'got {time_limit!r}'
    )
  # composer ends an episode once physics time >= time_limit, and the summed
  # physics timesteps fall just short of round numbers (40 x 0.1 s sums to
  # 3.9999...): without this margin a 4 s limit would run 41 steps.
  time_limit -= _TIME_LIMIT_MARGIN
  calibration = None
  if dynamics is not None:
    calibration = calibration_lib.resolve(dynamics)
    if robot is not None and not robot.virtual:
      raise ValueError(
        f'dynamics= calibrates a simulated robot; the robot on '
        f'{robot.device_path} has its own (no robot, or device_path '
        f'{constants.VIRTUAL_DEVICE!r})'
      )
  if robot is None:
    control_delay = 0.0
    if calibration is not None:
      robot = task_instance.robot
      calibration_lib.apply_to_model(
        calibration, domain, robot.joints, robot.actuators
      )
      control_delay = calibration.control_delay
    return Environment(
      task_instance,
      time_limit=time_limit,
      random_state=seed,
      control_delay=control_delay,
      calibration=calibration,
      **(environment_kwargs or {}),
    )
  # Imported here: the hardware layer needs the optional dynamixel_sdk.
  from robel_dm.hardware import environment as hardware  # noqa: PLC0415

  def simulated_scene() -> Environment:
    # The simulated robot behind a virtual bus: the same task, untimed.
    return _environment(
      domain,
      make_task,
      seed=seed,
      time_limit=math.inf,
      environment_kwargs=None,
      robot=None,
      dynamics=calibration,
    )

  return hardware.make_environment(
    task_instance,
    domain=domain,
    robot=robot,
    scene_factory=simulated_scene,
    time_limit=time_limit,
    random_state=seed,
    **(environment_kwargs or {}),
  )
