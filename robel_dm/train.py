r"""Trains a Stable-Baselines3 agent on a robel_dm task.

    python -m robel_dm.train --domain=dclaw --task=pose_fixed --steps=30000 \
        --seed=0 --output_dir=runs/pose

Writes into --output_dir:
  * `checkpoint.zip` (and `replay_buffer.pkl` for SAC): what --resume
    continues from;
  * `policy.npz`: the deterministic actor, for `robel_dm.policies.load` and
    `evaluate --policy=...` (numpy only);
  * `eval.jsonl`: one line per evaluation (env steps, wall time, success
    rate, mean score, mean return, mean safety violations per episode for
    position, velocity and current), with ROBEL's reward whatever
    --safety_penalty is;
  * `learning_curve.png`: success rate and score against env steps;
  * `config.json`: the flags of the run.

Needs the `learn` extra (Stable-Baselines3, a CPU build of torch,
Gymnasium, matplotlib).
"""

from collections.abc import Sequence
import json
import os
import pathlib
import sys
import time
from typing import Any

from absl import app, flags
import gymnasium
import numpy as np

from robel_dm import evaluate, policies, suite
from robel_dm import gym as robel_gym

ALGORITHMS = ('sac', 'ppo')
CHECKPOINT = 'checkpoint.zip'
REPLAY_BUFFER = 'replay_buffer.pkl'
POLICY = 'policy.npz'
EVAL_LOG = 'eval.jsonl'
CURVE = 'learning_curve.png'
CONFIG = 'config.json'
METADATA = 'metadata.json'


class SafetyPenalty(gymnasium.Wrapper):
  """Subtracts `penalty` per safety violation from the training reward."""

  def __init__(self, env: gymnasium.Env, penalty: float):
    super().__init__(env)
    self._penalty = penalty

  def step(self, action):
    observation, reward, terminated, truncated, info = self.env.step(action)
    violations = sum(info['safety'].values())
    return (
      observation,
      reward - self._penalty * violations,
      terminated,
      truncated,
      info,
    )


def make_env(
  domain: str,
  task: str,
  task_kwargs: dict | None,
  seed: int,
  safety_penalty: float = 0.0,
) -> gymnasium.Env:
  """A training environment (the penalty changes its reward only)."""
  env = robel_gym.RobelEnv(domain, task, task_kwargs=task_kwargs, seed=seed)
  if safety_penalty:
    env = SafetyPenalty(env, safety_penalty)
  return env


def _algorithm(name: str):
  from stable_baselines3 import PPO, SAC  # noqa: PLC0415 (torch)

  return {'sac': SAC, 'ppo': PPO}[name]


def build_model(
  algo: str,
  env,
  seed: int,
  hidden: Sequence[int],
  steps: int,
  learning_starts: int = 1000,
):
  """A Stable-Baselines3 agent with robel_dm's defaults (one torch
  thread; SAC's replay buffer no larger than the run)."""
  import torch  # noqa: PLC0415

  torch.set_num_threads(1)
  policy_kwargs = {'net_arch': list(hidden)}
  if algo == 'sac':
    return _algorithm('sac')(
      'MlpPolicy',
      env,
      seed=seed,
      policy_kwargs=policy_kwargs,
      buffer_size=max(steps, 1),
      learning_starts=min(learning_starts, max(steps // 10, 1)),
      verbose=0,
    )
  return _algorithm('ppo')(
    'MlpPolicy', env, seed=seed, policy_kwargs=policy_kwargs, verbose=0
  )


def numpy_policy(model, metadata: dict[str, Any]) -> policies.NumpyPolicy:
  """The deterministic actor of a SAC or PPO model as a `NumpyPolicy`."""
  from torch import nn  # noqa: PLC0415

  policy = model.policy
  if hasattr(policy, 'actor'):  # SAC: tanh of the mean.
    layers = [*policy.actor.latent_pi, policy.actor.mu]
    output = 'tanh'
  else:  # PPO: the mean, clipped to the action bounds.
    layers = [*policy.mlp_extractor.policy_net, policy.action_net]
    output = 'clip'
  linear = [layer for layer in layers if isinstance(layer, nn.Linear)]
  activations = {
    type(layer).__name__.lower()
    for layer in layers
    if not isinstance(layer, nn.Linear)
  }
  if len(activations) > 1 or not activations <= {'relu', 'tanh'}:
    raise ValueError(f'unsupported activations {activations}')
  return policies.NumpyPolicy(
    [layer.weight.detach().cpu().numpy() for layer in linear],
    [layer.bias.detach().cpu().numpy() for layer in linear],
    activations.pop() if activations else 'relu',
    output,
    metadata,
  )


def load_model(path: pathlib.Path, env=None):
  """Loads a SAC or PPO checkpoint (which one is recorded beside it)."""
  algo = read_metadata(path).get('algo', 'sac')
  return _algorithm(algo).load(str(path), env=env, device='cpu')


def read_metadata(path: pathlib.Path) -> dict[str, Any]:
  """The metadata saved beside a checkpoint (task, keys, algorithm)."""
  file = pathlib.Path(path).with_name(METADATA)
  if not file.is_file():
    raise policies.PolicyError(
      f'{file} is missing: the checkpoint does not say what it was trained on'
    )
  return json.loads(file.read_text())


def evaluate_policy(
  policy: policies.NumpyPolicy,
  domain: str,
  task: str,
  task_kwargs: dict | None,
  episodes: int,
  seed: int,
) -> dict[str, Any]:
  """ROBEL's metrics of a policy (ROBEL's reward, no penalty)."""
  results = evaluate.evaluate(
    domain,
    task,
    episodes,
    policy=policy,
    seed=seed,
    task_kwargs=task_kwargs,
  )
  return {
    'success_rate': results['success_rate'],
    'mean_score': results['mean_score'],
    'mean_return': results['mean_return'],
    'safety': results['safety'],
  }


def plot_curve(log_path: pathlib.Path, output: pathlib.Path, title: str):
  """Success rate and mean score against env steps."""
  import matplotlib  # noqa: PLC0415

  matplotlib.use('Agg')
  from matplotlib import pyplot  # noqa: PLC0415

  rows = [json.loads(line) for line in log_path.read_text().splitlines()]
  steps = [row['env_steps'] for row in rows]
  figure, axes = pyplot.subplots(1, 2, figsize=(9, 3.2))
  axes[0].plot(steps, [row['success_rate'] for row in rows], marker='o')
  axes[0].set(xlabel='env steps', ylabel='success rate', ylim=(-0.05, 1.05))
  axes[1].plot(steps, [row['mean_score'] for row in rows], marker='o')
  axes[1].set(xlabel='env steps', ylabel='mean score')
  figure.suptitle(title)
  figure.tight_layout()
  figure.savefig(output, dpi=100)
  pyplot.close(figure)


def train(
  domain: str,
  task: str,
  output_dir: str | pathlib.Path,
  *,
  task_kwargs: dict | None = None,
  algo: str = 'sac',
  steps: int = 30_000,
  seed: int = 0,
  num_envs: int = 1,
  eval_every: int = 5_000,
  eval_episodes: int = 10,
  safety_penalty: float = 0.0,
  resume: bool = False,
  hidden: Sequence[int] = (256, 256),
  log=print,
) -> list[dict[str, Any]]:
  """Trains, evaluating every `eval_every` env steps; see the module doc.

  Returns:
    The evaluation log (one dict per evaluation).

  Raises:
    ValueError: for bad arguments (unknown task or algorithm, steps < 1,
      a --resume without a checkpoint, or one of another task).
  """
  if algo not in ALGORITHMS:
    raise ValueError(f'algo must be one of {ALGORITHMS}, got {algo!r}')
  if steps < 1 or eval_every < 1 or eval_episodes < 1 or num_envs < 1:
    raise ValueError(
      'steps, eval_every, eval_episodes and num_envs must be >= 1'
    )
  if safety_penalty < 0 or not np.isfinite(safety_penalty):
    raise ValueError(f'safety_penalty must be >= 0, got {safety_penalty}')
  suite.load(domain, task, task_kwargs=task_kwargs).close()  # Checks names.
  from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: PLC0415

  output = pathlib.Path(output_dir)
  output.mkdir(parents=True, exist_ok=True)
  checkpoint = output / CHECKPOINT
  probe = robel_gym.RobelEnv(domain, task, task_kwargs=task_kwargs)
  metadata = {
    'domain': domain,
    'task': task,
    'task_kwargs': dict(task_kwargs or {}),
    'observation_keys': list(probe.observation_keys),
    'algo': algo,
    'seed': seed,
    'safety_penalty': safety_penalty,
  }
  probe.close()
  env = DummyVecEnv(
    [
      (
        lambda i=i: make_env(
          domain, task, task_kwargs, seed + i, safety_penalty
        )
      )
      for i in range(num_envs)
    ]
  )
  log_path = output / EVAL_LOG
  history = []
  wall_offset = 0.0
  if resume:
    if not checkpoint.is_file():
      raise ValueError(f'--resume: no checkpoint in {output}')
    trained = read_metadata(checkpoint)
    if (trained['domain'], trained['task']) != (domain, task):
      raise ValueError(
        f'--resume: {checkpoint} is for {trained["domain"]}/{trained["task"]}'
      )
    model = load_model(checkpoint, env)
    if algo == 'sac' and (output / REPLAY_BUFFER).is_file():
      model.load_replay_buffer(str(output / REPLAY_BUFFER))
    if log_path.is_file():
      history = [json.loads(line) for line in log_path.read_text().splitlines()]
      wall_offset = history[-1]['wall_time'] if history else 0.0
  else:
    model = build_model(algo, env, seed, hidden, steps)
    log_path.write_text('')
  # Stable-Baselines3's own logger would make a folder in /tmp per learn()
  # call; the evaluation log above is the record of the run.
  from stable_baselines3.common.logger import Logger  # noqa: PLC0415

  model.set_logger(Logger(folder=None, output_formats=[]))
  (output / CONFIG).write_text(
    json.dumps(
      {
        **metadata,
        'steps': steps,
        'num_envs': num_envs,
        'eval_every': eval_every,
        'eval_episodes': eval_episodes,
        'hidden': list(hidden),
      },
      indent=1,
    )
  )
  (output / METADATA).write_text(json.dumps(metadata, indent=1))
  start = time.perf_counter() - wall_offset
  while model.num_timesteps < steps:
    chunk = min(eval_every, steps - model.num_timesteps)
    model.learn(chunk, reset_num_timesteps=False)
    policy = numpy_policy(model, metadata)
    policy.save(output / POLICY)
    model.save(str(checkpoint))
    if algo == 'sac':
      model.save_replay_buffer(str(output / REPLAY_BUFFER))
    row = {
      'env_steps': int(model.num_timesteps),
      'wall_time': time.perf_counter() - start,
      **evaluate_policy(policy, domain, task, task_kwargs, eval_episodes, seed),
    }
    history.append(row)
    with open(log_path, 'a') as file:
      file.write(json.dumps(row) + '\n')
    log(
      f'{domain}/{task} {row["env_steps"]:>8d} steps '
      f'{row["wall_time"]:7.0f} s: success {row["success_rate"]:.2f} '
      f'score {row["mean_score"]:.3f} return {row["mean_return"]:9.1f} '
      'violations/episode '
      + ' '.join(f'{k} {v:.1f}' for k, v in row['safety'].items())
    )
  env.close()
  plot_curve(log_path, output / CURVE, f'{domain}/{task} ({algo}, seed {seed})')
  return history


def _define_flags() -> None:
  """The command line's flags (defined only when run as a program, so that
  importing this module defines none)."""
  flags.DEFINE_string('domain', 'dclaw', 'Task domain.')
  flags.DEFINE_string('task', 'pose_fixed', 'Task name in the domain.')
  flags.DEFINE_string(
    'task_kwargs', '', 'Task arguments: JSON or key=value,key=value.'
  )
  flags.DEFINE_enum('algo', 'sac', ALGORITHMS, 'Learning algorithm.')
  flags.DEFINE_integer('steps', 30_000, 'Env steps to train for.')
  flags.DEFINE_integer('seed', 0, 'Seed of the agent and the tasks.')
  flags.DEFINE_integer('num_envs', 1, 'Parallel environments.')
  flags.DEFINE_integer('eval_every', 5_000, 'Env steps per eval.')
  flags.DEFINE_integer('eval_episodes', 10, 'Episodes per eval.')
  flags.DEFINE_string('output_dir', None, 'Where to write the run.')
  flags.DEFINE_float(
    'safety_penalty', 0.0, 'Training reward minus this per safety violation.'
  )
  flags.DEFINE_bool('resume', False, 'Continue from the checkpoint.')
  flags.DEFINE_list('hidden', ['256', '256'], 'Hidden layer sizes.')


FLAGS = flags.FLAGS


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f'unexpected arguments: {argv[1:]}')
  if not FLAGS.output_dir:
    raise app.UsageError('--output_dir is required')
  os.environ.setdefault('MUJOCO_GL', 'egl')
  try:
    train(
      FLAGS.domain,
      FLAGS.task,
      FLAGS.output_dir,
      task_kwargs=evaluate.parse_task_kwargs(FLAGS.task_kwargs),
      algo=FLAGS.algo,
      steps=FLAGS.steps,
      seed=FLAGS.seed,
      num_envs=FLAGS.num_envs,
      eval_every=FLAGS.eval_every,
      eval_episodes=FLAGS.eval_episodes,
      safety_penalty=FLAGS.safety_penalty,
      resume=FLAGS.resume,
      hidden=[int(size) for size in FLAGS.hidden],
      log=lambda line: print(line, flush=True),
    )
  except ImportError as error:
    print(f'error: {error} (pip install "robel_dm[learn]")', file=sys.stderr)
    return 2
  except (ValueError, RuntimeError) as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  return 0


if __name__ == '__main__':
  _define_flags()
  app.run(main)
