r"""Trains an agent on a robel_dm task.

    robel-train --domain=dclaw --task=pose_fixed --steps=30000 \
        --seed=0 --output_dir=runs/pose

Writes into --output_dir:
  * `config.json`: the run's settings (`RunConfig`); --resume refuses to
    continue with different ones;
  * `checkpoint.zip`, `replay_buffer.pkl` (off-policy agents),
    `env_state.pkl` (each training environment's random stream and its
    episode in progress: where it began and its actions so far) and
    `random_streams.pkl` (torch's, numpy's and Python's): what --resume
    continues from, so that a resumed run equals the run never stopped;
  * `policy.npz`: the last deterministic actor, and `policy_best.npz`, the
    best evaluated one (success rate, then mean score), both for
    `robel_dm.policies.load` and `evaluate --policy=...` (numpy only);
  * `eval.jsonl`: one line per evaluation, the first before any learning
    (env steps, wall and CPU seconds, success rate, mean score, mean
    return, safety violations per episode), with ROBEL's reward whatever
    --safety_penalty is; evaluation episodes use seeds no training episode
    uses;
  * `learning_curve.png`;
  * `tensorboard/`: TensorBoard event files (`robel_dm.learning.telemetry`).

A directory that already holds a run is refused unless --resume continues
it or --overwrite starts it over (removing the run's files first).

Needs the `learn` extra.
"""

from collections.abc import Callable
import dataclasses
import json
import pathlib
import pickle
import time
from typing import Any

import numpy as np

from robel_dm import evaluation, policies, provenance, suite
from robel_dm.learning import (
  agents,
  curves,
  demos,
  extra,
  replay,
  safety,
  telemetry,
)

# A run's settings and files, by the names callers know here.
from robel_dm.learning.run_config import RESUMABLE_CHANGES, RunConfig
from robel_dm.learning.run_files import (
  BEST_POLICY,
  CHECKPOINT,
  CONFIG,
  CURVE,
  ENV_STATE,
  EVAL_LOG,
  METADATA,
  POLICY,
  RANDOM_STREAMS,
  REPLAY_BUFFER,
  check_output_dir,
  clear_output_dir,
  init_checkpoint,
)

try:
  import gymnasium
except ImportError as error:  # The optional learn extra.
  raise extra.missing(error) from error

# Evaluation episodes are seeded from here on, training ones below it.
EVAL_SEED_OFFSET = 1_000_000


class TrainingEnv(gymnasium.Wrapper):
  """A training environment: its episodes' random stream is its own, and
  the reward may pay a safety penalty.

  The stream is seeded once, when the environment is made; the seeds
  Stable-Baselines3 passes to `reset` are ignored, so a resumed run goes on
  with the stream it saved instead of starting it over. It keeps what its
  episode in progress began from and the actions taken since
  (`episode_state`), so that a resumed run can make that episode again to
  the step where it was saved (`resume_episode`) and go on as if it had
  never stopped.
  """

  def __init__(self, env, penalty: float):
    super().__init__(env)
    self._penalty = penalty
    self._start = None  # (random state, randomization scale) at reset.
    self._actions = []
    self._resumed = None  # What the next reset returns, after a resume.

  def reset(self, *, seed=None, options=None):
    del seed
    if self._resumed is not None:  # The episode `resume_episode` made.
      resumed, self._resumed = self._resumed, None
      return resumed
    robel = self.env.unwrapped
    self._start = (
      robel.robel_env.random_state.get_state(),
      robel.randomization_scale,
    )
    self._actions = []
    return self.env.reset(options=options)

  def step(self, action):
    self._actions.append(np.array(action, copy=True))
    observation, reward, terminated, truncated, info = self.env.step(action)
    if self._penalty:
      reward -= self._penalty * sum(info['safety'].values())
    return observation, reward, terminated, truncated, info

  def episode_state(self) -> dict[str, Any]:
    """What `resume_episode` needs: the episode's start, its actions so
    far, and the random stream as it stands."""
    return {
      'start': self._start,
      'actions': list(self._actions),
      'random_state': self.env.unwrapped.robel_env.random_state.get_state(),
    }

  def resume_episode(self, state: dict[str, Any]) -> bool:
    """Makes the saved episode again to where it was saved (the simulation
    is deterministic); the next `reset` goes on from there instead of
    starting an episode. False, with the random stream set where it was
    saved, if the episode made again does not end there (the next reset
    then starts a new episode from it)."""
    robel = self.env.unwrapped
    random_state, scale = state['start']
    robel.robel_env.random_state.set_state(random_state)
    if scale is not None and scale != robel.randomization_scale:
      robel.set_randomization_scale(scale)
    resumed = self.reset()
    for action in state['actions']:
      observation, _, _, _, info = self.step(action)
      resumed = observation, info
    now = robel.robel_env.random_state.get_state()
    if _same_random_state(now, state['random_state']):
      self._resumed = resumed
      return True
    robel.robel_env.random_state.set_state(state['random_state'])
    return False


def _same_random_state(a, b) -> bool:
  """Whether two `RandomState.get_state()` tuples are equal."""
  return all(
    np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y
    for x, y in zip(a, b, strict=True)
  )


def make_env(config: RunConfig, index: int) -> TrainingEnv:
  """Training environment `index` of a run."""
  from robel_dm.learning import gym as robel_gym  # noqa: PLC0415

  env = robel_gym.RobelEnv(
    config.domain,
    config.task,
    task_kwargs=config.training_task_kwargs,
    seed=config.seed * 1000 + index,
  )
  return TrainingEnv(env, config.safety_penalty)


def metadata_of(config: RunConfig) -> dict[str, Any]:
  """What a saved policy records about its training."""
  task_kwargs = config.policy_task_kwargs
  env = suite.load(config.domain, config.task, task_kwargs=task_kwargs)
  keys = list(env.task.agent_observation_keys)
  env.close()
  return {
    'domain': config.domain,
    'task': config.task,
    'task_kwargs': task_kwargs,
    'observation_keys': keys,
    'algo': config.algo,
    'seed': config.seed,
    'safety_penalty': config.safety_penalty,
    'safety_budget': config.budget,
    'init_from': config.init_from,
  }


def _eval_seed(config: RunConfig) -> int:
  return EVAL_SEED_OFFSET + config.seed * 1000


class Evaluations:
  """What a run's evaluations share: one simulated environment (each
  episode starts from a seeded reset, so the records equal a new
  environment's) and the provenance, read once, both made when first
  needed."""

  def __init__(self, config: RunConfig):
    self._config = config
    self._env = None
    self._provenance = None

  def reused(self) -> tuple[Any, dict[str, Any]]:
    """The run's evaluation environment and provenance."""
    if self._env is None:
      config = self._config
      self._env = suite.load(
        config.domain,
        config.task,
        seed=_eval_seed(config),
        task_kwargs=config.policy_task_kwargs,
      )
      self._provenance = provenance.describe()
    return self._env, self._provenance

  def close(self) -> None:
    if self._env is not None:
      self._env.close()
      self._env = None


def evaluate_policy(
  policy: policies.NumpyPolicy,
  config: RunConfig,
  episodes: int,
  evaluations: Evaluations | None = None,
) -> dict[str, Any]:
  """ROBEL's metrics of a policy (ROBEL's reward, no penalty), on
  episodes seeded apart from every training episode; in the environment of
  `evaluations` when given (a run's), else in a new one."""
  env, record = (None, None) if evaluations is None else evaluations.reused()
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      config.domain,
      config.task,
      episodes,
      policy=policy,
      seed=_eval_seed(config),
      task_kwargs=config.policy_task_kwargs,
    ),
    env=env,
    provenance_record=record,
  )
  return {
    'success_rate': results['success_rate'],
    'mean_score': results['mean_score'],
    'mean_return': results['mean_return'],
    'safety': results['safety'],
    'episodes': episodes,
  }


def within_budget(row: dict, budget: float | None) -> bool:
  """Whether an evaluation's safety violations per episode (all kinds
  summed) are within a run's safety `budget` (always, without one)."""
  return budget is None or sum(row['safety'].values()) <= budget


def _better(row: dict, best: dict | None, budget: float | None) -> bool:
  """Whether `row` beats the `best` evaluation so far (see `best_of`)."""
  if best is None:
    return True

  def merit(r):
    return within_budget(r, budget), r['success_rate'], r['mean_score']

  return merit(row) > merit(best)


def best_of(rows: list[dict], budget: float | None = None) -> dict | None:
  """The evaluation whose policy a run keeps as its best (higher success
  rate, then higher mean score; ties keep the earlier), or None. Under a
  safety `budget`, evaluations within it come first: a constrained run
  keeps the best policy that keeps its budget, if one does."""
  best = None
  for row in rows:
    if _better(row, best, budget):
      best = row
  return best


class Run:
  """The bookkeeping of one run directory: log, clocks, best policy."""

  def __init__(self, output: pathlib.Path, config: RunConfig, log):
    self.output, self.config, self.log = output, config, log
    self.log_path = output / EVAL_LOG
    self.telemetry = telemetry.Telemetry(
      output,
      f'{config.domain}/{config.task} {config.algo} seed {config.seed}',
      config.to_json(),
      config.steps,
      log,
    )
    self.history: list[dict] = []
    self.best: dict | None = None
    self._wall = self._cpu = self._evaluating = 0.0
    self.evaluations = Evaluations(config)

  def close(self) -> None:
    """Closes the run's telemetry and evaluation environment."""
    self.telemetry.close()
    self.evaluations.close()

  def load_history(self) -> None:
    if self.log_path.is_file():
      self.history = [
        json.loads(line) for line in self.log_path.read_text().splitlines()
      ]
    self.best = best_of(self.history, self.config.budget)
    if self.history:
      self._wall = self.history[-1]['wall_time']
      self._cpu = self.history[-1].get('cpu_time', 0.0)
      self._evaluating = self.history[-1].get('eval_time', 0.0)

  def solved(self, row: dict) -> bool:
    """Whether `row`, the last evaluation, ends the run early (see
    `stop_at_success`)."""
    target, streak = self.config.stop_at_success, self.config.stop_streak
    budget = self.config.budget

    def solved(r):  # Under a safety budget, only within it.
      return r['success_rate'] >= target and within_budget(r, budget)

    if target is None or not solved(row):
      return False
    recent = self.history[-streak:]
    return len(recent) == streak and all(map(solved, recent))

  def start_clocks(self) -> None:
    self._wall -= time.perf_counter()
    self._cpu -= time.process_time()

  def record(
    self,
    policy: policies.NumpyPolicy,
    steps: int,
    evaluator: Callable[[policies.NumpyPolicy], dict] | None = None,
    **extra,
  ) -> dict:
    """Evaluates `policy` (in simulation unless an `evaluator` is given),
    saves it (and as the best if it is), logs."""
    wall = self._wall + time.perf_counter()
    cpu = self._cpu + time.process_time()
    policy.save(self.output / POLICY)
    start = time.perf_counter()
    if evaluator is None:
      metrics = evaluate_policy(
        policy, self.config, self.config.eval_episodes, self.evaluations
      )
    else:
      metrics = evaluator(policy)
    row = {
      'env_steps': int(steps),
      'wall_time': wall,
      'cpu_time': cpu,
      # Evaluations so far (wall seconds, included in wall_time).
      'eval_time': self._evaluating,
      **extra,
      **metrics,
    }
    self._evaluating += time.perf_counter() - start
    if _better(row, self.best, self.config.budget):
      self.best = row
      policy.save(self.output / BEST_POLICY)
    self.history.append(row)
    with open(self.log_path, 'a') as file:
      file.write(json.dumps(row) + '\n')
    self.telemetry.evaluation(row)
    config = self.config
    self.log(
      f'{config.domain}/{config.task} {config.algo} seed {config.seed}: '
      # Behaviour cloning counts epochs, the others env steps.
      + (
        f'{row["epoch"]:>8d} epochs'
        if 'epoch' in row
        else f'{row["env_steps"]:>8d} steps'
      )
      + f' {row["wall_time"]:7.0f} s: success '
      f'{row["success_rate"]:.2f} score {row["mean_score"]:.3f} return '
      f'{row["mean_return"]:9.1f} violations/episode '
      + ' '.join(f'{k} {v:.1f}' for k, v in row['safety'].items())
    )
    return row


def check_resume(
  output: pathlib.Path, config: RunConfig, need_checkpoint: bool = True
) -> None:
  """Raises ValueError unless `output` holds a run of `config` (only the
  RESUMABLE_CHANGES may differ)."""
  path = output / CONFIG
  saved = (output / CHECKPOINT).is_file() or (output / POLICY).is_file()
  if need_checkpoint and not saved:
    raise ValueError(f'--resume: no checkpoint in {output}')
  if not path.is_file():
    raise ValueError(f'--resume: {path} is missing')
  saved = json.loads(path.read_text())
  trained = RunConfig.from_json(saved)
  built = saved.get('hyperparameters', config.agent.hyperparameters)
  if trained.algo == config.algo and built != config.agent.hyperparameters:
    raise ValueError(
      f'--resume: {output} was built with {trained.algo} settings {built}, '
      f'this robel_dm builds {config.agent.hyperparameters}; start a new run'
    )
  differences = [
    f'{name}: {getattr(trained, name)!r} (now {getattr(config, name)!r})'
    for name in (f.name for f in dataclasses.fields(RunConfig))
    if name not in RESUMABLE_CHANGES
    and _normalized(trained, name) != _normalized(config, name)
  ]
  if differences:
    raise ValueError(
      f'--resume: {output} was trained with other settings; pass the same '
      'ones (only --steps, --eval_every, --eval_episodes, '
      '--stop_at_success and --stop_streak may change): '
      + '; '.join(differences)
    )


def _normalized(config: RunConfig, name: str):
  value = getattr(config, name)
  if name == 'hidden':
    return config.layers
  if isinstance(value, dict):
    return json.dumps(value, sort_keys=True)
  return value


def _env_states(vec_env) -> list[dict[str, Any]]:
  return [env.episode_state() for env in vec_env.envs]


def _set_env_states(vec_env, states) -> bool:
  """Puts the training environments where `_env_states` found them: each
  makes its episode in progress again, for the model to go on from. A run
  saved before episodes were kept (a random state per environment), or
  whose episode does not replay, goes on from its random stream with a new
  episode. Returns whether every episode was made again."""
  if any(not isinstance(state, dict) for state in states):
    for env, state in zip(vec_env.envs, states, strict=True):
      env.unwrapped.robel_env.random_state.set_state(state)
    return False
  replayed = [
    env.resume_episode(state)
    for env, state in zip(vec_env.envs, states, strict=True)
  ]
  return all(replayed)


def _rollout(agent: agents.Agent, model, config: RunConfig) -> int:
  """Env steps the agent collects between updates (all environments)."""
  if agent.kind == agents.ON_POLICY:
    return int(model.n_steps) * config.num_envs
  return int(model.train_freq.frequency) * config.num_envs


def _round_up(value: int, unit: int) -> int:
  return -(-value // unit) * unit if unit else value


def train(
  config: RunConfig,
  output_dir: str | pathlib.Path,
  *,
  resume: bool = False,
  overwrite: bool = False,
  log: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
  """Trains, evaluating every `config.eval_every` env steps.

  Args:
    config: the run's settings.
    output_dir: where the run's files go.
    resume: continue the run `output_dir` holds.
    overwrite: start over in an `output_dir` that holds a run, removing
      its files (`RUN_FILES`, TensorBoard events) first.
    log: where progress lines go.

  Returns:
    The evaluation log (one dict per evaluation).

  Raises:
    ValueError: for bad settings, an `output_dir` holding a run without
      `resume` or `overwrite` (or both asked), a --resume without a
      checkpoint or with other settings, or unusable demonstrations; all
      before anything is written.
  """
  config.check()
  output = pathlib.Path(output_dir)
  check_output_dir(output, resume, overwrite)
  agents.check_installed(config.agent)
  metadata = metadata_of(config)  # Also checks the task's name.
  if resume:
    check_resume(output, config)
  data = load_data(config, tuple(metadata['observation_keys']))
  if overwrite:
    clear_output_dir(output)
  output.mkdir(parents=True, exist_ok=True)
  run = Run(output, config, log)
  if resume:
    run.load_history()
  else:
    run.log_path.write_text('')
  (output / CONFIG).write_text(json.dumps(config.to_json(), indent=1))
  (output / METADATA).write_text(json.dumps(metadata, indent=1))
  try:
    if config.agent.kind == agents.IMITATION:
      _clone(config, run, data, metadata)
    else:
      _reinforce(config, run, data, metadata, resume)
  finally:
    run.close()
  curves.plot_run(
    run.log_path,
    output / CURVE,
    f'{config.domain}/{config.task} ({config.algo}, seed {config.seed})',
  )
  return run.history


def load_data(
  config: RunConfig, keys: tuple[str, ...]
) -> demos.Transitions | None:
  """The run's demonstrations and recordings as one set of transitions
  (None if it has neither)."""
  parts = []
  if config.demos:
    parts.append(
      demos.load(
        list(config.demos),
        config.domain,
        config.task,
        keys,
        config.task_kwargs,
        config.demo_episodes,
      )
    )
  if config.from_recording:
    parts.append(
      demos.load(
        list(config.from_recording),
        config.domain,
        config.task,
        keys,
        config.task_kwargs,
        complete_only=False,
      )
    )
  return demos.concatenate(parts) if parts else None


def _clone(config: RunConfig, run: Run, data, metadata) -> None:
  from robel_dm.learning import imitation  # noqa: PLC0415

  done = run.history[-1]['epoch'] if run.history else 0
  if done >= config.steps:
    return
  hyper = config.agent.hyperparameters
  run.start_clocks()
  if not run.history:
    untrained = imitation.fit_policy(
      data,
      imitation.FitConfig(config.layers, config.seed, 0, 1, 1e-3),
      metadata,
    )
    run.record(untrained, 0, epoch=0, demo_transitions=len(data))
  # Behaviour cloning is cheap: a resumed run starts over from the data.
  fit = imitation.FitConfig(
    config.layers,
    config.seed,
    config.steps,
    hyper['batch_size'],
    hyper['learning_rate'],
    every=config.eval_every,
  )

  def on_epoch(epoch, policy, loss):
    # The epochs a resumed run already logged are fitted again, not logged
    # again.
    if epoch > done:
      run.record(policy, 0, epoch=epoch, loss=loss, demo_transitions=len(data))

  imitation.fit_policy(data, fit, metadata, on_epoch)


def _reinforce(config: RunConfig, run: Run, data, metadata, resume) -> None:
  agent = config.agent
  output = run.output
  from stable_baselines3.common.logger import Logger  # noqa: PLC0415
  from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: PLC0415

  vec_env = DummyVecEnv(
    [lambda i=i: make_env(config, i) for i in range(config.num_envs)]
  )
  checkpoint = output / CHECKPOINT
  if resume and checkpoint.is_file():
    model = _resumed_model(config, run, vec_env, data)
  else:
    model = _new_model(config, vec_env, data)
  if config.budget is not None and model.safety is None:
    model.safety = safety.SafetyConstraint(config.budget)
  # SB3's own logger would make a folder in /tmp per learn() call; its
  # values go to the run's TensorBoard events and progress lines instead.
  output_format = telemetry.agent_log_output(
    run.telemetry, lambda: model.num_timesteps
  )
  model.set_logger(Logger(folder=None, output_formats=[output_format]))
  rollout = _rollout(agent, model, config)
  eval_every = _round_up(config.eval_every, rollout)
  steps = _round_up(config.steps, rollout)
  if steps != config.steps:
    run.log(
      f'{config.algo} collects whole rollouts of {rollout} env steps: '
      f'training for {steps} steps, evaluating every {eval_every}'
    )
  run.start_clocks()
  if not run.history:
    run.record(agents.numpy_policy(model, metadata), 0)
  while model.num_timesteps < steps:
    chunk = min(eval_every, steps - model.num_timesteps)
    if agent.curriculum:
      vec_env.env_method(
        'set_randomization_scale',
        curriculum_scale(agent.curriculum, model.num_timesteps, steps),
      )
    model.learn(chunk, reset_num_timesteps=False)
    _save(model, agent, output, vec_env)
    row = run.record(agents.numpy_policy(model, metadata), model.num_timesteps)
    if run.solved(row):
      break
  vec_env.close()


def _save(model, agent: agents.Agent, output: pathlib.Path, vec_env) -> None:
  """What `_resumed_model` goes on from: the model, its replay buffer, the
  training episodes in progress and the shared random streams."""
  model.save(str(output / CHECKPOINT))
  if agent.replay:
    model.save_replay_buffer(str(output / REPLAY_BUFFER))
  with open(output / ENV_STATE, 'wb') as file:
    pickle.dump(_env_states(vec_env), file)
  with open(output / RANDOM_STREAMS, 'wb') as file:
    pickle.dump(agents.shared_random_streams(), file)


def _resumed_model(config: RunConfig, run: Run, vec_env, data):
  """The model `_save` left in the run's folder, with its replay buffer
  (grown to the run's budget), the training episodes in progress made
  again and the shared random streams where they were."""
  output, agent = run.output, config.agent
  model = agents.load(agent, output / CHECKPOINT, vec_env)
  if agent.replay and (output / REPLAY_BUFFER).is_file():
    model.load_replay_buffer(str(output / REPLAY_BUFFER))
    replay.grow(model, config.steps + _demo_count(data))
  if (output / ENV_STATE).is_file():
    with open(output / ENV_STATE, 'rb') as file:
      states = pickle.load(file)
    if not _set_env_states(vec_env, states):
      run.log(
        'resuming with a new training episode (the one in progress '
        'when the run was saved could not be made again)'
      )
  # Loading the model seeded them again from the run's seed.
  if (output / RANDOM_STREAMS).is_file():
    with open(output / RANDOM_STREAMS, 'rb') as file:
      agents.set_shared_random_streams(pickle.load(file))
  return model


def curriculum_scale(share: float, done: int, steps: int) -> float:
  """The randomization scale of a curriculum over the first `share` of a
  run of `steps` env steps, `done` of them made: rising linearly from 0
  to 1, then 1."""
  return min(1.0, done / (share * steps))


def _new_model(config: RunConfig, vec_env, data):
  """The model of a run's start: built, or taken from --init_from; the
  demonstrations and recordings stored in its replay buffer."""
  buffer_size = config.steps + _demo_count(data)
  if config.init_from:
    model = agents.warm_start(
      config.agent,
      init_checkpoint(config.init_from),
      vec_env,
      config.seed,
      buffer_size,
    )
  else:
    model = agents.build(
      config.agent, vec_env, config.seed, config.layers, buffer_size
    )
  if data is not None:
    # One environment (RunConfig.check); the buffer's size (run steps +
    # these) keeps them for the run.
    replay.store(model.replay_buffer, data)
  return model


def _demo_count(data) -> int:
  return 0 if data is None else len(data)
