r"""Evaluates a policy on a robel_dm task and reports ROBEL's metrics.

    python -m robel_dm.evaluate --domain=dclaw --task=pose_fixed \
        --policy=reference --episodes=20 --output=results.json

Prints one row per episode and a summary, and optionally writes JSON with the
success rate (ROBEL's success evaluator: the `success` signal at each
episode's last step), mean return, mean score, mean safety violations per
episode and the control steps per second.
"""

from collections.abc import Sequence
import contextlib
import math
import os
import sys
import time
from typing import Any

from absl import app, flags, logging
import numpy as np
import tqdm

from robel_dm import (
  cli_checks,
  gl_backend,
  parallel,
  policies,
  provenance,
  recording,
  result_table,
  robots,
  rollout,
  suite,
  task_args,
  video,
)
from robel_dm.tasks import base

# A frame slower than this is software rendering: the note says so.
SLOW_FRAME_SECONDS = 0.05


def summarize(
  records: list[dict[str, Any]], head: dict[str, Any], steps_per_second
) -> dict[str, Any]:
  """The result of a run: `head`, the means and spreads, the records."""

  def values(key):
    return [r[key] for r in records]

  requested = head.get('episodes_requested', len(records))
  return {
    **head,
    'episodes': len(records),
    # False while a run is under way, and in the output of a run cut short.
    'complete': len(records) >= requested,
    'success_rate': float(np.mean(values('success'))) if records else math.nan,
    'mean_return': float(np.mean(values('return'))) if records else math.nan,
    'mean_score': float(np.mean(values('mean_score'))) if records else math.nan,
    'mean_final_score': float(np.mean(values('final_score')))
    if records
    else math.nan,
    'safety': {
      field: float(np.mean([r['safety'][field] for r in records]))
      if records
      else math.nan
      for field in base.SAFETY_FIELDS
    },
    'spread': {
      'success': provenance.proportion(values('success')),
      'return': provenance.spread(values('return')),
      'mean_score': provenance.spread(values('mean_score')),
    },
    'steps_per_second': steps_per_second,
    'records': records,
  }


# The flags that make a `suite.RobotOptions` (with --device_path).
ROBOT_OPTION_FLAGS = ('robot_config', 'reset', 'guide', 'tracker')


def robot_options(flag_values) -> suite.RobotOptions | None:
  """The robot --device_path and ROBOT_OPTION_FLAGS name; None simulates.

  Raises:
    ValueError: for one of those flags without --device_path, or a bad
      value.
  """
  fields = {name: flag_values[name].value for name in ROBOT_OPTION_FLAGS}
  if not flag_values['device_path'].value:
    given = [name for name, value in fields.items() if value is not None]
    if given:
      raise ValueError(
        f'--{given[0]} needs --device_path (it is about a robot)'
      )
    return None
  return suite.RobotOptions(flag_values['device_path'].value, **fields)


def evaluate(
  domain: str,
  task: str,
  episodes: int,
  policy: str | policies.Policy = 'random',
  seed: int | None = 0,
  task_kwargs: dict[str, Any] | None = None,
  log_every: int = 0,
  robot: suite.RobotOptions | None = None,
  on_episode=None,
  video_dir: str | None = None,
  camera: str | None = None,
  workers: int = 1,
  ray_address: str | None = None,
  record: str | None = None,
  dynamics: str | None = None,
  allow_other_seed: bool = False,
  video_episodes: Sequence[int] | None = None,
  log=None,
) -> dict[str, Any]:
  """Runs `episodes` episodes and returns the metrics.

  Episode i starts from a reset seeded with `seed + i` (the policy's own
  randomness from `seed`), so any episode can be reproduced on its own.

  Args:
    domain: task domain, e.g. 'dclaw'.
    task: task name, e.g. 'turn_fixed'.
    episodes: number of episodes (>= 1).
    policy: a name or path (see `policies.make_policy`), or a callable from
      timestep to action (a `policies.NumpyPolicy` is checked against the
      task).
    seed: seed of the episodes and the policy; None draws fresh ones.
    task_kwargs: task arguments for `suite.load`.
    log_every: log progress every this many episodes (0: never).
    robot: run on this robot (`suite.RobotOptions`: device, configuration,
      reset, guide motor, tracker); None simulates.
    on_episode: called with the results so far after every episode (to
      print rows and save partial results as they come).
    video_dir: write one MP4 per episode here (`robel_dm.video`).
    camera: the videos' camera; the domain's default if None.
    workers: run the episodes in this many local processes (simulation,
      a policy given by name or path); the records equal a serial run's.
    ray_address: run the episodes as tasks of a Ray cluster: its address
      ('auto' for the one this machine belongs to), or 'local' to start
      one here; the records equal a serial run's.
    record: record every timestep into this recording directory
      (`robel_dm.recording`; checked before anything moves).
    dynamics: a calibration file of the simulated robot (see
      `suite.load` and docs/sysid.md).
    allow_other_seed: replay a recording ('replay:DIR') from another seed
      than its own (refused otherwise, before anything is built).
    video_episodes: with `video_dir`, film only these episodes (indices
      from 0); None films every one.
    log: called with a line to show the user (how videos are rendered,
      and how long they will take); None: no such lines.

  Returns:
    A JSON-serializable dict of per-episode records, summary metrics,
    spreads and provenance (software versions, git revision, time,
    machine).

  Raises:
    ValueError: for bad arguments (unknown task or policy, episodes < 1).
  """
  if episodes < 1:
    raise ValueError(f'episodes must be >= 1, got {episodes}')
  if video_episodes is not None:
    outside = sorted(set(video_episodes) - set(range(episodes)))
    if outside:
      raise ValueError(
        f'video episodes {outside} are not among the {episodes} episodes '
        f'(0..{episodes - 1})'
      )
    if video_dir is None:
      raise ValueError('video episodes need a video folder (--video=DIR)')
  if workers < 1:
    raise ValueError(f'workers must be >= 1, got {workers}')
  replay = isinstance(policy, str) and policy.startswith(policies.REPLAY)
  if (workers > 1 or ray_address) and (
    callable(policy)
    or replay  # Each worker would replay from the recording's start.
    or robot
    or video_dir
    or record
    or dynamics
    or seed is None
  ):
    raise ValueError(
      'workers > 1 and ray_address need a simulated task, a seed, no video, '
      'no dynamics, and a policy given by name or path (not a replay)'
    )
  # A policy file is read and checked against the task before anything is
  # built (and a robot moves); None for policies that are not files.
  checked = policies.check_file(policy, domain, task, task_kwargs)
  if replay:
    checked = policies.ReplayPolicy(
      policy[len(policies.REPLAY) :], domain, task, task_kwargs, seed,
      episodes=episodes, check_seed=not allow_other_seed,
    )  # fmt: skip
  env = suite.load(
    domain,
    task,
    seed=seed,
    task_kwargs=task_kwargs,
    robot=robot,
    dynamics=dynamics,
  )
  if record is not None:
    try:
      env = recording.Recorder(
        env,
        record,
        metadata={
          'domain': domain,
          'task': task,
          'task_kwargs': task_kwargs or {},
          'seed': seed,
          'policy': policy if isinstance(policy, str) else repr(policy),
          'device_path': robot and robot.device_path,
          'dynamics': dynamics,
        },
      )
    except recording.RecordingError:
      env.close()
      raise
  head = {
    'domain': domain,
    'task': task,
    'task_kwargs': task_kwargs or {},
    'policy': policy if isinstance(policy, str) else repr(policy),
    'seed': seed,
    'device_path': robot and robot.device_path,
    'dynamics': dynamics,
    'episodes_requested': episodes,
    'provenance': provenance.describe(),
  }
  records, total_steps, step_seconds = [], 0, 0.0

  def results():
    rate = total_steps / step_seconds if step_seconds else math.nan
    return summarize(records, head, rate)

  try:
    if callable(policy):
      act = policy
      if isinstance(policy, policies.NumpyPolicy):
        policy.check_task(domain, task, task_kwargs)
    elif checked is not None:
      act = checked
    else:
      act = policies.make_policy(policy, env, seed, domain, task, task_kwargs)
    if workers > 1 or ray_address:
      env.close()
      run = parallel.ray_episodes if ray_address else parallel.local_episodes
      for episode_record, steps, seconds in run(
        domain, task, task_kwargs, policy, seed, episodes,
        ray_address or workers,
      ):  # fmt: skip
        records.append(episode_record)
        total_steps += steps
        step_seconds += seconds
        if on_episode is not None:
          on_episode(results())
      return results()
    filmed = set(range(episodes) if video_episodes is None else video_episodes)
    if video_dir is not None:
      camera = camera or robots.ROBOTS[domain].default_camera
      video.check_camera(env, camera)
      os.makedirs(video_dir, exist_ok=True)
      if log is not None:
        log(_rendering_note(env, camera, len(filmed)))
    for episode in range(episodes):
      episode_seed = None if seed is None else seed + episode
      writer = on_step = None
      if video_dir is not None and episode in filmed:
        path = os.path.join(video_dir, f'{domain}_{task}_{episode:04d}.mp4')
        writer = video.VideoWriter(path, fps=1 / env.control_timestep())

        def on_step(writer=writer):
          writer.add(video.render(env, camera))

      if policy == 'random':  # Each episode's actions from its own seed.
        act = policies.make_policy(policy, env, episode_seed)
      if isinstance(env, recording.Recorder):  # What a replay checks.
        env.annotate(episode_seed=episode_seed)
      try:
        episode_record, steps, seconds = rollout.run_episode(
          env, act, episode_seed, on_step
        )
      finally:
        if writer is not None:
          writer.close()
      if writer is not None:
        episode_record['video'] = path
      records.append(episode_record)
      total_steps += steps
      step_seconds += seconds
      if on_episode is not None:
        on_episode(results())
      if log_every and (episode + 1) % log_every == 0:
        logging.info(
          '%s/%s: %d/%d episodes, success so far %.2f',
          domain,
          task,
          episode + 1,
          episodes,
          np.mean([r['success'] for r in records]),
        )
  finally:
    env.close()
  return results()


def _rendering_note(env, camera: str, videos: int) -> str:
  """How videos are rendered here and what they will cost: one line."""
  video.render(env, camera)  # The first frame also sets the renderer up.
  start = time.perf_counter()
  video.render(env, camera)
  seconds = time.perf_counter() - start
  steps = env.task.episode_steps
  minutes = seconds * (steps + 1) * videos / 60
  note = (
    f'videos: camera {camera}, {gl_backend.describe()}; {seconds:.2f} s a '
    f'frame here, about {minutes:.1f} min for {videos} episode(s) of '
    f'{steps} steps'
  )
  if seconds > SLOW_FRAME_SECONDS:
    note += ' (software rendering: --video_episodes films fewer)'
  return note


def _define_flags() -> None:
  """The command line's flags (defined only when run as a program, so that
  importing this module defines none)."""
  flags.DEFINE_string('domain', 'dclaw', "Task domain, or 'all'.")
  flags.DEFINE_string(
    'task', 'pose_fixed', "Task name in the domain, or 'all' (a sweep)."
  )
  flags.DEFINE_bool('list', False, 'List the tasks and exit.')
  flags.DEFINE_string(
    'tracker',
    None,
    "With --device_path, the D'Kitty's motion tracker: "
    'natnet:SERVER[:PORT],rigid_body=ID[,target=ID,heading=ID,'
    'multicast=GROUP|unicast,data_port=N,local=ADDR,version=4.1,y_up=true].',
  )
  flags.DEFINE_string(
    'record', None, 'Record every timestep into this directory.'
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
  flags.DEFINE_integer('episodes', 10, 'Number of episodes.', lower_bound=1)
  flags.DEFINE_integer('seed', 0, 'Seed of the environment and policy.')
  flags.DEFINE_string(
    'policy',
    'random',
    'Policy to evaluate: random, zero, reference (scripted), baseline (the '
    "task's shipped trained policy), or the path of a policy.npz written "
    'by robel_dm.train.',
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
  flags.DEFINE_string(
    'task_kwargs',
    '',
    'Task arguments: a JSON object (\'{"valve": "valve4"}\') or '
    'comma-separated key=value pairs (valve=valve4).',
  )
  flags.DEFINE_string('output', None, 'Write the results here (JSON).')
  flags.DEFINE_string(
    'dynamics',
    None,
    'A calibration of the simulated robot (python -m robel_dm.sysid fit); '
    'simulation or --device_path=virtual.',
  )
  flags.DEFINE_string(
    'device_path',
    None,
    'Run on a robot: its Dynamixel bus (e.g. /dev/ttyUSB0, or the path '
    'printed by `python -m robel_dm.tools.virtual_bus`), or "virtual" for '
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


FLAGS = flags.FLAGS


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


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f'unexpected arguments: {argv[1:]}')
  if FLAGS.list:
    print(_list_tasks())
    return 0
  finished: list[dict[str, Any]] = []
  try:
    task_kwargs = task_args.parse_task_kwargs(FLAGS.task_kwargs)
    tasks = task_args.select_tasks(FLAGS.domain, FLAGS.task)
    video_episodes = _video_episodes(FLAGS.video_episodes)
    cli_checks.check_output(FLAGS.output, _read_files(tasks))
    if len(tasks) > 1:  # A sweep runs the tasks the policy can run.
      reasons = {
        t: task_args.unavailable(FLAGS.policy, *t, task_kwargs) for t in tasks
      }
      for (domain, task), reason in reasons.items():
        if reason:
          print(f'skipped {domain}/{task}: {reason}', file=sys.stderr)
      tasks = [t for t in tasks if not reasons[t]]
      if not tasks:
        raise ValueError(f'no selected task can run policy {FLAGS.policy!r}')
    checked = {  # Every task's policy file, before any runs.
      (domain, task): policies.check_file(
        FLAGS.policy, domain, task, task_kwargs, FLAGS.allow_other_variant
      )
      for domain, task in tasks
    }
    sweep = len(tasks) > 1
    progress = tqdm.tqdm(
      total=len(tasks) * FLAGS.episodes, unit='episode', file=sys.stderr,
      disable=not sys.stderr.isatty(),
    )  # fmt: skip

    saved = [0]  # Episodes in --output.
    latest = []  # The results of the task under way, as last saved.

    def save(partial):
      latest[:] = [partial]
      # Saved, then printed: a printed row is in --output whenever Ctrl-C
      # lands (a failed write stops the run, unprinted).
      if FLAGS.output:
        everything = [*finished, partial]
        cli_checks.save(
          FLAGS.output, everything if sweep else partial, saved[0]
        )
        saved[0] = sum(len(r['records']) for r in everything)
      progress.update(1)
      progress.clear()
      if len(partial['records']) == 1:
        print(result_table.format_header(partial), flush=True)
      index = len(partial['records']) - 1
      print(result_table.format_row(index, partial['records'][-1]), flush=True)
      progress.refresh()

    robot = robot_options(FLAGS)
    for domain, task in tasks:
      results = evaluate(
        domain,
        task,
        FLAGS.episodes,
        policy=(FLAGS.allow_other_variant and checked[domain, task])
        or FLAGS.policy,
        seed=FLAGS.seed,
        task_kwargs=task_kwargs,
        robot=robot,
        on_episode=save,
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
      finished.append(results)
      latest.clear()
      print(result_table.format_summary(results), flush=True)
    progress.close()
  except (ValueError, RuntimeError) as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  except KeyboardInterrupt:
    # A robot's motors were released on the way out (see hardware.shutdown);
    # every finished episode is in --output already: mark it cut short.
    print('interrupted', file=sys.stderr)
    if FLAGS.output and (finished or latest):
      cut = [dict(r, interrupted=True) for r in latest] or [
        dict(finished.pop(), interrupted=True)
      ]
      everything = [*finished, *cut]
      cli_checks.save(
        FLAGS.output, everything if sweep else everything[-1], saved[0]
      )
      print(
        f'{FLAGS.output} holds {saved[0]} episode(s), marked interrupted',
        file=sys.stderr,
      )
    return 130
  if FLAGS.output:
    print(f'wrote {FLAGS.output}')
  return 0


if __name__ == '__main__':
  _define_flags()
  app.run(main)
