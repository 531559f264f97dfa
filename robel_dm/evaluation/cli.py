"""The evaluation command's flags and main (`robel-evaluate`, run by
`robel_dm.commands.evaluate`).

`define_flags` defines the flags (only when the command runs, so that
importing this module defines none); `main` checks them, runs the selected
tasks with `evaluation.evaluate`, prints a row per episode and a summary
per task, and saves the results to --output as they come.
"""

import contextlib
import sys
from typing import Any

from absl import app, flags
import tqdm

from robel_dm import evaluation, policies, suite
from robel_dm.evaluation import checks, table, task_args

FLAGS = flags.FLAGS

# The command's description, which --help shows.
HELP = r"""Evaluates a policy on a robel_dm task and reports ROBEL's metrics.

    robel-evaluate --domain=dclaw --task=pose_fixed \
        --policy=reference --episodes=20 --output=results.json

Prints one row per episode and a summary, and optionally writes JSON with the
success rate (ROBEL's success evaluator: the `success` signal at each
episode's last step), mean return, mean score, mean safety violations per
episode and the control steps per second.
"""

# The flags that make a `suite.RobotOptions` (with --device_path).
ROBOT_OPTION_FLAGS = ('robot_config', 'reset', 'guide', 'tracker')


def define_flags() -> None:
  """Defines the command line's flags."""
  _define_task_flags()
  _define_policy_flags()
  _define_output_flags()
  _define_robot_flags()


def _define_task_flags() -> None:
  """What runs: the tasks, episodes, seed, and where."""
  flags.DEFINE_string('domain', 'dclaw', "Task domain, or 'all'.")
  flags.DEFINE_string(
    'task', 'pose_fixed', "Task name in the domain, or 'all' (a sweep)."
  )
  flags.DEFINE_bool('list', False, 'List the tasks and exit.')
  flags.DEFINE_integer('episodes', 10, 'Number of episodes.', lower_bound=1)
  flags.DEFINE_integer('seed', 0, 'Seed of the environment and policy.')
  flags.DEFINE_string(
    'task_kwargs',
    '',
    'Task arguments: a JSON object (\'{"valve": "valve4"}\') or '
    'comma-separated key=value pairs (valve=valve4).',
  )
  flags.DEFINE_string(
    'ray_address',
    None,
    "Run the episodes on a Ray cluster: its address, 'auto', or 'local' to "
    'start one here.',
  )
  flags.DEFINE_integer(
    'workers',
    1,
    'Run the episodes in this many local processes.',
    lower_bound=1,
  )
  flags.DEFINE_string(
    'dynamics',
    None,
    'A calibration of the simulated robot (robel-sysid fit); '
    'simulation or --device_path=virtual.',
  )


def _define_policy_flags() -> None:
  """The policy, and what it may run on."""
  flags.DEFINE_string(
    'policy',
    'random',
    'Policy to evaluate: random, zero, reference (scripted), baseline (the '
    "task's shipped trained policy), or the path of a policy.npz written "
    'by robel-train.',
  )
  flags.DEFINE_bool(
    'allow_other_variant',
    False,
    'Run a policy file on another variant of the task it was trained on '
    "(e.g. a Fixed task's policy on the Random one).",
  )
  flags.DEFINE_bool(
    'allow_other_seed',
    False,
    'Replay a recording (--policy=replay:DIR) from another seed than its own.',
  )


def _define_output_flags() -> None:
  """What the run writes: results, recording, videos."""
  flags.DEFINE_string('output', None, 'Write the results here (JSON).')
  flags.DEFINE_string(
    'record', None, 'Record every timestep into this directory.'
  )
  flags.DEFINE_string(
    'video', None, 'Write one MP4 per episode into this folder.'
  )
  flags.DEFINE_string(
    'camera',
    None,
    "The videos' camera (default: dclaw front, dkitty follow).",
  )
  flags.DEFINE_list(
    'video_episodes',
    None,
    'With --video: film only these episodes (indices from 0, e.g. 0,5); '
    'default: every episode. Rendering without a GPU takes about 0.4 s a '
    'frame.',
  )


def _define_robot_flags() -> None:
  """The robot (--device_path) and ROBOT_OPTION_FLAGS."""
  flags.DEFINE_string(
    'device_path',
    None,
    'Run on a robot: its Dynamixel bus (e.g. /dev/ttyUSB0, or the path '
    'printed by `robel-virtual-bus`), or "virtual" for '
    'an in-process simulated bus. Default: simulation.',
  )
  flags.DEFINE_string(
    'robot_config', None, 'Robot configuration file (JSON) for --device_path.'
  )
  flags.DEFINE_enum(
    'reset',
    None,
    ['scripted', 'move', 'manual'],
    "With --device_path: how the robot is reset (default: the robot's).",
  )
  flags.DEFINE_enum(
    'guide',
    None,
    ['show', 'interactive'],
    "With --device_path, D'Claw Turn/Screw: the guide motor shows the goal, "
    'or a person turns it to set the goal.',
  )
  flags.DEFINE_string(
    'tracker',
    None,
    "With --device_path, the D'Kitty's motion tracker: "
    'natnet:SERVER[:PORT],rigid_body=ID[,target=ID,heading=ID,'
    'multicast=GROUP|unicast,data_port=N,local=ADDR,version=4.1,y_up=true].',
  )


def check_device_path(flag_values: flags.FlagValues) -> None:
  """Raises ValueError for a --device_path given empty (an empty `$(...)`
  in a shell): never read as "simulate"."""
  device = flag_values['device_path']
  if device.present and not (device.value or '').strip():
    raise ValueError(
      "--device_path is empty: give the robot's serial device (e.g. "
      "/dev/ttyUSB0) or 'virtual', or leave the flag out to simulate"
    )


def robot_options(
  flag_values: flags.FlagValues, names: tuple[str, ...] = ROBOT_OPTION_FLAGS
) -> suite.RobotOptions | None:
  """The robot --device_path and the flags `names` describe; None simulates.

  Args:
    flag_values: parsed flags holding --device_path and `names` (this
      command's, or another command's that defines them).
    names: the command's flags of `suite.RobotOptions` fields (by default
      ROBOT_OPTION_FLAGS, all of them).

  Raises:
    ValueError: for one of those flags without --device_path, an empty
      --device_path, or a bad value.
  """
  fields = {name: flag_values[name].value for name in names}
  check_device_path(flag_values)
  if not flag_values['device_path'].value:
    given = [name for name, value in fields.items() if value is not None]
    if given:
      raise ValueError(
        f'--{given[0]} needs --device_path (it is about a robot)'
      )
    return None
  return suite.RobotOptions(flag_values['device_path'].value, **fields)


def _video_episodes(values: list[str] | None) -> list[int] | None:
  """--video_episodes as indices (checked against --episodes and --video)."""
  if values is None:
    return None
  try:
    indices = [int(v) for v in values]
  except ValueError:
    raise ValueError(
      f'--video_episodes={",".join(values)}: give episode indices, e.g. 0,5'
    ) from None
  if not FLAGS.video:
    raise ValueError('--video_episodes needs --video=DIR')
  if any(i < 0 or i >= FLAGS.episodes for i in indices):
    raise ValueError(
      f'--video_episodes={",".join(values)}: indices run from 0 to '
      f'{FLAGS.episodes - 1} (--episodes={FLAGS.episodes})'
    )
  return indices


def _read_files(tasks) -> list[tuple[str, str | None]]:
  """(flag, path) of the files a run of `tasks` reads: --output must name
  none of them."""
  files = [
    ('--dynamics', FLAGS.dynamics),
    ('--robot_config', FLAGS.robot_config),
  ]
  policy = FLAGS.policy
  if policy == policies.BASELINE:
    for domain, task in tasks:
      with contextlib.suppress(policies.PolicyError):  # Said later.
        files.append(('--policy', str(policies.baseline_path(domain, task))))
  elif policy not in policies.BUILT_IN and not policy.startswith(
    policies.REPLAY
  ):
    files.append(('--policy', policy))
  return files


def _list_tasks() -> str:
  return '\n'.join(
    f'{domain:<7} {", ".join(tasks)}'
    for domain, tasks in suite.TASKS_BY_DOMAIN.items()
  )


def _runnable(
  tasks: list[tuple[str, str]], task_kwargs: dict[str, Any]
) -> list[tuple[str, str]]:
  """The tasks of a sweep that the policy can run (each skipped one said
  on stderr); a single task as it is.

  Raises:
    ValueError: if the policy can run none of them.
  """
  if len(tasks) <= 1:
    return tasks
  reasons = {
    t: task_args.unavailable(FLAGS.policy, *t, task_kwargs) for t in tasks
  }
  for (domain, task), reason in reasons.items():
    if reason:
      print(f'skipped {domain}/{task}: {reason}', file=sys.stderr)
  tasks = [t for t in tasks if not reasons[t]]
  if not tasks:
    raise ValueError(f'no selected task can run policy {FLAGS.policy!r}')
  return tasks


class _Output:
  """The results of the run's tasks as they come: each episode saved to
  --output, then printed as a row; each task's summary printed."""

  def __init__(self, tasks: int):
    """Starts with nothing saved.

    Args:
      tasks: how many tasks run (more than one: --output holds a list).
    """
    self.finished: list[dict[str, Any]] = []  # The finished tasks' results.
    self.latest: list[dict[str, Any]] = []  # The task under way's, as saved.
    self.saved = 0  # Episodes in --output.
    self.sweep = tasks > 1
    self.progress = tqdm.tqdm(
      total=tasks * FLAGS.episodes, unit='episode', file=sys.stderr,
      disable=not sys.stderr.isatty(),
    )  # fmt: skip

  def episode(self, partial: dict[str, Any]) -> None:
    """Saves, then prints, the task under way's results after an episode."""
    self.latest[:] = [partial]
    # Saved, then printed: a printed row is in --output whenever Ctrl-C
    # lands (a failed write stops the run, unprinted).
    if FLAGS.output:
      everything = [*self.finished, partial]
      checks.save(
        FLAGS.output, everything if self.sweep else partial, self.saved
      )
      self.saved = sum(len(r['records']) for r in everything)
    self.progress.update(1)
    self.progress.clear()
    if len(partial['records']) == 1:
      print(table.format_header(partial), flush=True)
    index = len(partial['records']) - 1
    print(table.format_row(index, partial['records'][-1]), flush=True)
    self.progress.refresh()

  def task_done(self, results: dict[str, Any]) -> None:
    """Keeps a finished task's results and prints its summary."""
    self.finished.append(results)
    self.latest.clear()
    print(table.format_summary(results), flush=True)

  def interrupted(self) -> None:
    """Marks the results in --output cut short (every finished episode is
    there already)."""
    if not (FLAGS.output and (self.finished or self.latest)):
      return
    cut = [dict(r, interrupted=True) for r in self.latest] or [
      dict(self.finished.pop(), interrupted=True)
    ]
    everything = [*self.finished, *cut]
    checks.save(
      FLAGS.output, everything if self.sweep else everything[-1], self.saved
    )
    print(
      f'{FLAGS.output} holds {self.saved} episode(s), marked interrupted',
      file=sys.stderr,
    )


def _checked_files(
  tasks: list[tuple[str, str]], task_kwargs: dict[str, Any]
) -> dict[tuple[str, str], policies.Policy | None]:
  """Every task's policy file, read and checked before any task runs
  (None where the policy is not a file)."""
  return {
    (domain, task): policies.check_file(
      FLAGS.policy, domain, task, task_kwargs, FLAGS.allow_other_variant
    )
    for domain, task in tasks
  }


def _config(
  domain: str,
  task: str,
  policy: str | policies.Policy,
  task_kwargs: dict[str, Any],
  video_episodes: list[int] | None,
  robot: suite.RobotOptions | None,
  on_episode,
) -> evaluation.EvalConfig:
  """The evaluation of one task, as the flags ask."""
  return evaluation.EvalConfig(
    domain,
    task,
    FLAGS.episodes,
    policy=policy,
    seed=FLAGS.seed,
    task_kwargs=task_kwargs,
    robot=robot,
    on_episode=on_episode,
    video_dir=FLAGS.video,
    camera=FLAGS.camera,
    workers=FLAGS.workers,
    ray_address=FLAGS.ray_address,
    record=FLAGS.record,
    dynamics=FLAGS.dynamics,
    allow_other_seed=FLAGS.allow_other_seed,
    video_episodes=video_episodes,
    log=lambda line: print(line, file=sys.stderr, flush=True),
  )


def _check_flags_apply() -> None:
  """Raises ValueError for a flag that would have no effect here."""
  replay = FLAGS.policy.startswith(policies.REPLAY)
  built_in = replay or FLAGS.policy in policies.BUILT_IN
  for flag, useless, needs in (
    ('--camera', FLAGS.camera and not FLAGS.video, '--video=DIR (it films)'),
    ('--allow_other_seed', FLAGS.allow_other_seed and not replay,
     '--policy=replay:DIR'),
    ('--allow_other_variant', FLAGS.allow_other_variant and built_in,
     'a policy file (or baseline)'),
  ):  # fmt: skip
    if useless:
      raise ValueError(f'{flag} needs {needs}')


def main(argv: list[str]) -> int:
  """The command: 0 when done, 2 for bad input or a failure (one line on
  stderr), 130 when interrupted."""
  if len(argv) > 1:
    raise app.UsageError(f'unexpected arguments: {argv[1:]}')
  if FLAGS.list:
    print(_list_tasks())
    return 0
  output = None  # Once every task is checked.
  try:
    task_kwargs = task_args.parse_task_kwargs(FLAGS.task_kwargs)
    tasks = task_args.select_tasks(FLAGS.domain, FLAGS.task)
    video_episodes = _video_episodes(FLAGS.video_episodes)
    _check_flags_apply()
    checks.check_output(FLAGS.output, _read_files(tasks))
    tasks = _runnable(tasks, task_kwargs)
    checked = _checked_files(tasks, task_kwargs)
    output = _Output(len(tasks))
    robot = robot_options(FLAGS)
    for domain, task in tasks:
      policy = (FLAGS.allow_other_variant and checked[domain, task]) or (
        FLAGS.policy
      )
      config = _config(
        domain, task, policy, task_kwargs, video_episodes, robot,
        output.episode,
      )  # fmt: skip
      output.task_done(evaluation.evaluate(config))
    output.progress.close()
  except (ValueError, RuntimeError, ImportError) as error:
    # An ImportError names the extra to install (e.g. robel_dm[hardware]).
    print(f'error: {error}', file=sys.stderr)
    return 2
  except KeyboardInterrupt:
    # A robot's motors were released on the way out (see hardware.shutdown);
    # every finished episode is in --output already: mark it cut short.
    print('interrupted', file=sys.stderr)
    if output is not None:
      output.interrupted()
    return 130
  if FLAGS.output:
    print(f'wrote {FLAGS.output}')
  return 0
