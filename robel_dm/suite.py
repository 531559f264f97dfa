"""Loads robel_dm tasks as dm_env environments.

    from robel_dm import suite
    env = suite.load('dclaw', 'turn_fixed', seed=0)

`suite.load` is the only place that wraps tasks in an environment, so the
performance-critical settings (compile the MJCF once, batch substeps, strip
singleton observation dimensions) are the same for every task.
"""

from collections.abc import Callable
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
from robel_dm.tasks import (  # noqa: F401  (imported to register the tasks)
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


def _unknown(kind: str, name: str, known) -> ValueError:
  known = sorted(known)
  close = difflib.get_close_matches(name, known, n=1)
  hint = f' Did you mean {close[0]!r}?' if close else ''
  return ValueError(f'unknown {kind} {name!r}; expected one of {known}.{hint}')


def _one_of(value, alias, name: str):
  """`value`, or dm_control.suite's `<name>_name` keyword in its place."""
  if value is not None and alias is not None and value != alias:
    raise ValueError(f'both {name}={value!r} and {name}_name={alias!r} given')
  if value is None and alias is None:
    raise ValueError(f'{name} is required')
  return value if value is not None else alias


def load(
  domain: str | None = None,
  task: str | None = None,
  task_kwargs: dict[str, Any] | None = None,
  environment_kwargs: dict[str, Any] | None = None,
  *,
  seed: int | None = None,
  time_limit: float | None = None,
  device_path: str | None = None,
  robot_config=None,
  reset: str | None = None,
  tracker=None,
  guide: str | None = None,
  dynamics: Dynamics | None = None,
  domain_name: str | None = None,
  task_name: str | None = None,
  visualize_reward: bool = False,
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
    device_path: run on a real robot: the Dynamixel bus's serial device
      (e.g. '/dev/ttyUSB0'), or 'virtual' for an in-process virtual bus
      driven by a simulation. None (default) simulates.
    robot_config: with `device_path`: a `RobotConfig` or the path of a JSON
      robot configuration; ROBEL's configuration of the domain by default.
    reset: with `device_path`: 'scripted', 'move' or 'manual' (see
      `robel_dm.hardware.resets`); the robot's default if None.
    tracker: with `device_path`: a
      `robel_dm.hardware.tracking.tracker.TorsoTracker` giving the D'Kitty's
      torso pose (and Orient/Walk targets).
    guide: with `device_path`, for D'Claw Turn/Screw: ROBEL's guide motor
      'show's the goal, or ('interactive') a person turns it to set the
      goal.
    dynamics: a calibration (file path or `calibration.Calibration`, e.g.
      from `python -m robel_dm.sysid fit`) of the simulated robot's joint
      dynamics and control delay. With device_path='virtual' it calibrates
      the simulation behind the virtual bus; a real robot has its own.
    domain_name: `dm_control.suite.load`'s name for `domain`.
    task_name: `dm_control.suite.load`'s name for `task`.
    visualize_reward: accepted for `dm_control.suite` code; robel_dm shows
      goal markers instead and draws no reward colours.

  Returns:
    A `dm_env.Environment` (a `composer.Environment`).

  Raises:
    ValueError: for an unknown domain, task or task argument.
    calibration.CalibrationError: for a malformed calibration or one of
      another robot.
  """
  del visualize_reward  # See the docstring.
  domain = _one_of(domain, domain_name, 'domain')
  task = _one_of(task, task_name, 'task')
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
    device_path=device_path,
    dynamics=dynamics,
    hardware_options={
      'robot_config': robot_config,
      'reset': reset,
      'tracker': tracker,
      'guide': guide,
    },
  )


def load_excitation(
  domain: str,
  duration: float,
  *,
  seed: int | None = None,
  device_path: str | None = None,
  robot_config=None,
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
    device_path: a robot's bus (or 'virtual'), as for `load`.
    robot_config: with `device_path`, as for `load`.
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
    device_path=device_path,
    dynamics=dynamics,
    hardware_options={'robot_config': robot_config},
  )


def _environment(
  domain: str,
  make_task: Callable[[], base.RobelTask],
  *,
  seed,
  time_limit,
  environment_kwargs,
  device_path,
  dynamics,
  hardware_options,
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
    if device_path not in (None, constants.VIRTUAL_DEVICE):
      raise ValueError(
        f'dynamics= calibrates a simulated robot; the robot on '
        f'{device_path} has its own (device_path=None or '
        f'{constants.VIRTUAL_DEVICE!r})'
      )
  if device_path is None:
    given = [name for name, value in hardware_options.items() if value]
    if given:
      raise ValueError(f'{", ".join(given)} need a device_path (a robot)')
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
      device_path=None,
      dynamics=calibration,
      hardware_options={},
    )

  return hardware.make_environment(
    task_instance,
    domain=domain,
    device_path=device_path,
    scene_factory=simulated_scene,
    time_limit=time_limit,
    random_state=seed,
    **hardware_options,
    **(environment_kwargs or {}),
  )
