r"""Evaluates a policy on a robel_dm task and reports ROBEL's metrics.

    python -m robel_dm.evaluate --domain=dclaw --task=pose_fixed \
        --policy=reference --episodes=20 --output=results.json

Prints one row per episode and a summary, and optionally writes JSON with the
success rate (ROBEL's success evaluator: the `success` signal at each
episode's last step), mean return, mean score, mean safety violations per
episode and the control steps per second.
"""

import json
import math
import sys
import time
from typing import Any

from absl import app, flags, logging
import numpy as np

from robel_dm import policies, suite
from robel_dm.tasks import base


def parse_task_kwargs(text: str) -> dict[str, Any]:
  """Parses --task_kwargs: a JSON object or comma-separated key=value pairs.

  Values of key=value pairs are read as JSON where possible (numbers, true,
  null, lists), otherwise as strings.

  Raises:
    ValueError: if the text is neither form.
  """
  text = text.strip()
  if not text:
    return {}
  if text.startswith('{'):
    try:
      parsed = json.loads(text)
    except json.JSONDecodeError as error:
      raise ValueError(f'--task_kwargs is not valid JSON: {error}') from error
    if not isinstance(parsed, dict):
      raise ValueError('--task_kwargs JSON must be an object')
    return parsed
  kwargs = {}
  for pair in text.split(','):
    key, sep, value = pair.partition('=')
    if not sep or not key.strip():
      raise ValueError(f'--task_kwargs entry {pair!r} is not key=value')
    try:
      kwargs[key.strip()] = json.loads(value)
    except json.JSONDecodeError:
      kwargs[key.strip()] = value.strip()
  return kwargs


def evaluate(
  domain: str,
  task: str,
  episodes: int,
  policy: str | policies.Policy = 'random',
  seed: int | None = 0,
  task_kwargs: dict[str, Any] | None = None,
  log_every: int = 0,
  device_path: str | None = None,
  robot_config: str | None = None,
  reset: str | None = None,
  guide: str | None = None,
) -> dict[str, Any]:
  """Runs `episodes` episodes and returns the metrics.

  Args:
    domain: task domain, e.g. 'dclaw'.
    task: task name, e.g. 'turn_fixed'.
    episodes: number of episodes (>= 1).
    policy: a name or path (see `policies.make_policy`), or a callable from
      timestep to action (a `policies.NumpyPolicy` is checked against the
      task).
    seed: seed of the environment and the policy.
    task_kwargs: task arguments for `suite.load`.
    log_every: log progress every this many episodes (0: never).
    device_path: run on a robot (see `suite.load`); None simulates.
    robot_config: robot configuration file for `device_path`.
    reset: reset procedure for `device_path` (see `suite.load`).
    guide: guide motor mode for `device_path` (see `suite.load`).

  Returns:
    A JSON-serializable dict of per-episode records and summary metrics.

  Raises:
    ValueError: for bad arguments (unknown task or policy, episodes < 1).
  """
  if episodes < 1:
    raise ValueError(f'episodes must be >= 1, got {episodes}')
  env = suite.load(
    domain,
    task,
    seed=seed,
    task_kwargs=task_kwargs,
    device_path=device_path,
    robot_config=robot_config,
    reset=reset,
    guide=guide,
  )
  try:
    if callable(policy):
      act = policy
      if isinstance(policy, policies.NumpyPolicy):
        policy.check_task(domain, task, task_kwargs)
    else:
      act = policies.make_policy(policy, env, seed, domain, task, task_kwargs)
    records = []
    step_seconds = 0.0
    total_steps = 0
    for episode in range(episodes):
      timestep = env.reset()
      episode_return, scores = 0.0, []
      safety = np.zeros(len(base.SAFETY_FIELDS), dtype=np.int64)
      while not timestep.last():
        action = act(timestep)
        start = time.perf_counter()
        timestep = env.step(action)
        step_seconds += time.perf_counter() - start
        total_steps += 1
        episode_return += timestep.reward
        scores.append(float(timestep.observation[base.SCORE]))
        safety += timestep.observation[base.SAFETY]
      records.append(
        {
          'return': episode_return,
          'mean_score': float(np.mean(scores)),
          'final_score': scores[-1],
          'success': bool(timestep.observation[base.SUCCESS]),
          'steps': len(scores),
          'safety': dict(zip(base.SAFETY_FIELDS, safety.tolist(), strict=True)),
        }
      )
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
  return {
    'domain': domain,
    'task': task,
    'task_kwargs': task_kwargs or {},
    'policy': policy if isinstance(policy, str) else repr(policy),
    'seed': seed,
    'episodes': episodes,
    'success_rate': float(np.mean([r['success'] for r in records])),
    'mean_return': float(np.mean([r['return'] for r in records])),
    'mean_score': float(np.mean([r['mean_score'] for r in records])),
    'mean_final_score': float(np.mean([r['final_score'] for r in records])),
    'safety': {
      field: float(np.mean([r['safety'][field] for r in records]))
      for field in base.SAFETY_FIELDS
    },
    'steps_per_second': total_steps / step_seconds
    if step_seconds
    else math.nan,
    'device_path': device_path,
    'records': records,
  }


def format_table(results: dict[str, Any]) -> str:
  """Formats the results as a plain-text table."""
  header = (
    f'{"episode":>7} {"return":>10} {"mean score":>10} {"success":>7} '
    f'{"pos/vel/cur violations":>22}'
  )
  lines = [
    f'{results["domain"]}/{results["task"]}  policy={results["policy"]}  '
    f'seed={results["seed"]}  task_kwargs={results["task_kwargs"]}',
    header,
    '-' * len(header),
  ]
  for i, record in enumerate(results['records']):
    safety = '/'.join(str(v) for v in record['safety'].values())
    lines.append(
      f'{i:>7} {record["return"]:>10.2f} {record["mean_score"]:>10.3f} '
      f'{"yes" if record["success"] else "no":>7} {safety:>22}'
    )
  safety = results['safety']
  lines += [
    '-' * len(header),
    f'success rate      {results["success_rate"]:.2f} '
    f'({results["episodes"]} episodes)',
    f'mean return       {results["mean_return"]:.2f}',
    f'mean score        {results["mean_score"]:.3f}',
    'safety / episode  '
    + ', '.join(f'{field} {value:.2f}' for field, value in safety.items()),
    f'steps per second  {results["steps_per_second"]:.0f}',
  ]
  return '\n'.join(lines)


def _define_flags() -> None:
  """The command line's flags (defined only when run as a program, so that
  importing this module defines none)."""
  flags.DEFINE_string('domain', 'dclaw', 'Task domain.')
  flags.DEFINE_string('task', 'pose_fixed', 'Task name in the domain.')
  flags.DEFINE_integer('episodes', 10, 'Number of episodes.', lower_bound=1)
  flags.DEFINE_integer('seed', 0, 'Seed of the environment and policy.')
  flags.DEFINE_string(
    'policy',
    'random',
    'Policy to evaluate: random, zero, reference (scripted), baseline (the '
    "task's shipped trained policy), or the path of a policy.npz or a "
    'Stable-Baselines3 .zip written by robel_dm.train.',
  )
  flags.DEFINE_string(
    'task_kwargs',
    '',
    'Task arguments: a JSON object (\'{"valve": "valve4"}\') or '
    'comma-separated key=value pairs (valve=valve4).',
  )
  flags.DEFINE_string('output', None, 'Write the results here (JSON).')
  flags.DEFINE_string(
    'device_path',
    None,
    'Run on a robot: its Dynamixel bus (e.g. /dev/ttyUSB0, or the path '
    'printed by `python -m robel_dm.hardware.virtual`), or "virtual" for '
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


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f'unexpected arguments: {argv[1:]}')
  try:
    task_kwargs = parse_task_kwargs(FLAGS.task_kwargs)
    results = evaluate(
      FLAGS.domain,
      FLAGS.task,
      FLAGS.episodes,
      policy=FLAGS.policy,
      seed=FLAGS.seed,
      task_kwargs=task_kwargs,
      log_every=max(1, FLAGS.episodes // 10),
      device_path=FLAGS.device_path,
      robot_config=FLAGS.robot_config,
      reset=FLAGS.reset,
      guide=FLAGS.guide,
    )
  except (ValueError, RuntimeError) as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  except KeyboardInterrupt:
    # A robot's motors were released on the way out (see hardware.shutdown).
    print('interrupted', file=sys.stderr)
    return 130
  print(format_table(results))
  if FLAGS.output:
    with open(FLAGS.output, 'w') as f:
      json.dump(results, f, indent=2)
    print(f'wrote {FLAGS.output}')
  return 0


if __name__ == '__main__':
  _define_flags()
  app.run(main)
