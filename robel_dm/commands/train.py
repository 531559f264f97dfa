r"""Trains an agent on a robel_dm task (see `robel_dm.learning.training`).

    robel-train --domain=dclaw --task=pose_fixed --steps=30000 \
        --seed=0 --output_dir=runs/pose
    robel-train --algo=bc --demos=runs/demos ...
    # On a robot (or a virtual bus), in real time:
    robel-train --domain=dclaw --task=pose_fixed \
        --device_path=/dev/ttyUSB0 --hours=2 --output_dir=runs/claw

`--algo` is one of `robel_dm.learning.agents.AGENTS` (SAC on JAX by
default). Needs the `learn` extra.
"""

import os
import signal
import sys

from absl import app, flags

from robel_dm import command_help, constants
from robel_dm.learning import agents


def _define_flags() -> None:
  """The command line's flags (defined only when run as a program, so that
  importing this module defines none)."""
  _define_run_flags()
  _define_learning_flags()
  _define_robot_flags()


def _define_run_flags() -> None:
  """The task, the agent, its budget and evaluations, the run's folder."""
  flags.DEFINE_string('domain', 'dclaw', 'Task domain.')
  flags.DEFINE_string('task', 'pose_fixed', 'Task name in the domain.')
  flags.DEFINE_string(
    'task_kwargs', '', 'Task arguments: JSON or key=value,key=value.'
  )
  flags.DEFINE_enum(
    'algo',
    agents.DEFAULT,
    sorted(agents.AGENTS),
    f'Learning agent ({agents.DEFAULT} in simulation, {agents.ROBOT_DEFAULT} '
    'with --device_path unless given).',
  )
  flags.DEFINE_integer('steps', 30_000, 'Env steps (bc: epochs).')
  flags.DEFINE_integer('seed', 0, 'Seed of the agent and the tasks.')
  flags.DEFINE_integer('num_envs', 1, 'Parallel environments.')
  flags.DEFINE_integer(
    'eval_every', 5_000, 'Env steps (bc: epochs) per evaluation.'
  )
  flags.DEFINE_integer('eval_episodes', 10, 'Episodes per evaluation.')
  flags.DEFINE_string('output_dir', None, 'Where to write the run.')
  flags.DEFINE_bool('resume', False, 'Continue from the checkpoint.')
  flags.DEFINE_bool(
    'overwrite',
    False,
    'Start over in an --output_dir that holds a run (removes its files).',
  )


def _define_learning_flags() -> None:
  """How the agent learns: safety, starting point, networks, demonstrations,
  when to stop."""
  flags.DEFINE_float(
    'safety_penalty', 0.0, 'Training reward minus this per safety violation.'
  )
  flags.DEFINE_float(
    'safety_budget',
    None,
    'Learn to keep safety violations per episode (all kinds) at most this '
    'many, with a learned price per violation (sbx SAC agents).',
  )
  flags.DEFINE_string(
    'init_from',
    None,
    "Start from another run's networks: its folder or checkpoint.zip (sbx "
    'SAC agents; e.g. the Random variant for RandomDynamics).',
  )
  flags.DEFINE_list('hidden', [], "Hidden layer sizes (the agent's if empty).")
  flags.DEFINE_list(
    'demos', [], 'Recordings of demonstrations (bc and sac_demos).'
  )
  flags.DEFINE_integer('demo_episodes', 20, 'Demonstration episodes to use.')
  flags.DEFINE_float(
    'stop_at_success',
    None,
    'End early once an evaluation reaches this success rate.',
  )
  flags.DEFINE_integer(
    'stop_streak',
    1,
    'With --stop_at_success: evaluations in a row that must reach it.',
  )
  flags.DEFINE_list(
    'from_recording',
    [],
    'Recordings whose every transition starts the replay buffer (or joins '
    "bc's data).",
  )


def _define_robot_flags() -> None:
  """Learning on a robot (robel_dm.learning.robot_training)."""
  flags.DEFINE_string(
    'device_path',
    None,
    "Learn on a robot: its Dynamixel bus (a virtual bus's pty), or "
    "'virtual' for an in-process simulated bus.",
  )
  flags.DEFINE_string('robot_config', None, 'With --device_path: robot file.')
  flags.DEFINE_enum(
    'reset',
    None,
    ['scripted', 'move', 'manual'],
    "With --device_path: the reset procedure (default: the robot's).",
  )
  flags.DEFINE_enum(
    'guide', None, ['show', 'interactive'], 'With --device_path: guide motor.'
  )
  flags.DEFINE_string(
    'tracker', None, "With --device_path: the D'Kitty's tracker spec."
  )
  flags.DEFINE_string(
    'dynamics', None, 'With --device_path=virtual: calibration file.'
  )
  flags.DEFINE_float('hours', None, 'With --device_path: wall-clock budget.')
  flags.DEFINE_bool(
    'safe_defaults',
    True,
    'With --device_path: act through the safe action map and learn under a '
    'budget of 10 safety violations per episode, unless --task_kwargs, '
    '--safety_budget or --safety_penalty say otherwise '
    "(--nosafe_defaults: ROBEL's map, no budget).",
  )
  flags.DEFINE_integer(
    'max_violations',
    None,
    'With --device_path: end an episode at this many safety violations.',
  )
  flags.DEFINE_integer(
    'reset_attempts',
    3,
    'With --device_path: failed resets in a row that stop the run.',
  )
  flags.DEFINE_float(
    'updates_per_step',
    None,
    'With --device_path: gradient updates per robot step, at most (default: '
    "the agent's own, sac 1, droq 10).",
  )
  flags.DEFINE_bool(
    'wait_for_learner',
    None,
    'With --device_path: the robot waits for the learner after every step '
    '(default: only on the simulated-time bus, --device_path=virtual).',
  )


# Flags of a run on a robot beyond the robot itself (the evaluation
# command's ROBOT_OPTION_FLAGS).
_ROBOT_RUN_FLAGS = ('dynamics', 'hours', 'max_violations', 'reset_attempts',
                    'updates_per_step', 'wait_for_learner')  # fmt: skip


# Flags that only mean something beside another one.
_NEEDS_PARTNER = {'stop_streak': 'stop_at_success', 'demo_episodes': 'demos'}

FLAGS = flags.FLAGS


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f'unexpected arguments: {argv[1:]}')
  if not FLAGS.output_dir:
    raise app.UsageError('--output_dir is required')
  os.environ.setdefault('MUJOCO_GL', 'egl')
  from robel_dm.evaluation import cli  # noqa: PLC0415

  try:
    _check_partners()
    config = _run_config()
    log = lambda line: print(line, flush=True)  # noqa: E731
    robot_options = cli.robot_options(FLAGS)
    if robot_options is not None:
      _train_on_robot(config, robot_options, log)
    else:
      _train_in_simulation(config, log)
  except ImportError as error:
    named = str(error)
    if constants.INSTALL_EXTRA.split('{}')[0] in named and (
      constants.INSTALL_EXTRA.format('learn') not in named
    ):
      # Another extra, which it names (e.g. the hardware).
      print(f'error: {error}', file=sys.stderr)
      return 2
    print(
      f'error: training needs the learn extra '
      f'({(error.name or "a package").split(".")[0]} is missing): '
      + constants.INSTALL_EXTRA.format('learn'),
      file=sys.stderr,
    )
    return 2
  except (ValueError, RuntimeError) as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  except KeyboardInterrupt:
    print(_stopped('Ctrl-C'), file=sys.stderr)
    return 130
  except SystemExit as stop:
    # An exit signal (SIGTERM, SIGHUP, SIGQUIT) released the robot and ends
    # the program through SystemExit(128 + signal): say what stays.
    if isinstance(stop.code, int) and stop.code - 128 in _EXIT_SIGNALS:
      print(_stopped(_EXIT_SIGNALS[stop.code - 128]), file=sys.stderr)
    raise
  return 0


def _algo() -> str:
  """The agent: the flag's if given, else the default of where it runs."""
  if FLAGS['algo'].present or FLAGS.device_path is None:
    return FLAGS.algo
  return agents.ROBOT_DEFAULT


def _check_partners() -> None:
  """Raises ValueError for a flag given without the one it works with."""
  for name, partner in _NEEDS_PARTNER.items():
    if FLAGS[name].present and FLAGS[partner].value in (None, []):
      raise ValueError(f'--{name} needs --{partner} (alone it does nothing)')


def _run_config():
  """The flags' `learning.training.RunConfig`."""
  from robel_dm.evaluation import task_args  # noqa: PLC0415
  from robel_dm.learning import run_config  # noqa: PLC0415
  from robel_dm.learning import training as learning  # noqa: PLC0415

  return learning.RunConfig(
    domain=FLAGS.domain,
    task=FLAGS.task,
    task_kwargs=task_args.parse_task_kwargs(FLAGS.task_kwargs),
    algo=_algo(),
    seed=FLAGS.seed,
    steps=FLAGS.steps,
    num_envs=FLAGS.num_envs,
    eval_every=FLAGS.eval_every,
    eval_episodes=FLAGS.eval_episodes,
    safety_penalty=FLAGS.safety_penalty,
    safety_budget=FLAGS.safety_budget,
    init_from=FLAGS.init_from,
    hidden=run_config.parse_hidden(FLAGS.hidden),
    demos=tuple(FLAGS.demos),
    demo_episodes=FLAGS.demo_episodes,
    stop_at_success=FLAGS.stop_at_success,
    stop_streak=FLAGS.stop_streak,
    from_recording=tuple(FLAGS.from_recording),
  )


def _train_on_robot(config, robot_options, log) -> None:
  """Learns `config`'s task on the robot of `robot_options` (the flags'
  `suite.RobotOptions`), in real time."""
  from robel_dm.learning import robot_training  # noqa: PLC0415

  if FLAGS.safe_defaults:
    config = robot_training.with_safe_defaults(config)
  options = robot_training.RobotRunOptions(
    robot_options,
    **{name: FLAGS[name].value for name in _ROBOT_RUN_FLAGS},
  )
  robot_training.train_on_robot(
    config,
    options,
    FLAGS.output_dir,
    resume=FLAGS.resume,
    overwrite=FLAGS.overwrite,
    log=log,
  )


def _train_in_simulation(config, log) -> None:
  """Learns `config`'s task in simulation; refuses the robot-only flags."""
  from robel_dm.learning import training as learning  # noqa: PLC0415

  given = [
    name for name in (*_ROBOT_RUN_FLAGS, 'safe_defaults') if FLAGS[name].present
  ]
  if given:
    raise ValueError(f'--{given[0]} needs --device_path (it is about a robot)')
  learning.train(
    config,
    FLAGS.output_dir,
    resume=FLAGS.resume,
    overwrite=FLAGS.overwrite,
    log=log,
  )


_EXIT_SIGNALS = {
  int(signal.SIGTERM): 'SIGTERM',
  int(signal.SIGHUP): 'SIGHUP',
  int(signal.SIGQUIT): 'SIGQUIT',
}


def _stopped(cause: str) -> str:
  """What a run stopped by `cause` kept, and how to go on."""
  if FLAGS.algo == 'bc':
    kept = (
      'the policy of the last evaluation is kept (--resume fits again from '
      'the demonstrations)'
    )
    if FLAGS.device_path:
      kept = f'the robot is released (torque off); {kept}'
  elif FLAGS.device_path:
    kept = (
      'the robot is released (torque off); the networks are saved and '
      'every robot step is in the recording'
    )
  else:
    kept = "the networks of the last evaluation's checkpoint are kept"
  return (
    f'stopped by {cause}: {kept} in {FLAGS.output_dir}; the same command '
    'with --resume continues'
  )


def run() -> None:
  """The command (`robel-train`, or `python -m robel_dm.commands.train`)."""
  command_help.run_absl(_define_flags, main, __doc__, __name__)


if __name__ == '__main__':
  run()
