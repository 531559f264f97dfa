r"""Learning on a robot, in real time (`train --device_path=...`).

    robel-train --domain=dclaw --task=pose_fixed \
        --device_path=/dev/ttyUSB0 --steps=8000 --output_dir=runs/claw

Two processes share the work. This one (the *actor*) runs the robot: every
control step it computes the action from the newest actor weights it has
(numpy, microseconds), steps the robot at the task's control period, writes
the transition to the run's recording and hands it to the *learner*. The
learner, a process of its own so that its gradient updates never hold up a
control step, keeps the replay buffer, updates the networks (at most
`updates_per_step` updates per recorded transition) and sends new actor
weights back a few times a second.

Episodes: the task's reset runs between episodes (the robot's reset
procedure); an episode whose safety violations reach `max_violations` ends
early. A hardware fault ends its episode (the motors are released by the
robot layer), is logged and counted; training goes on after the next
successful reset, and stops, saved, after `reset_attempts` failed resets in
a row. Ctrl-C or SIGTERM stops the run saved, with torque off.

Every step is in `<output_dir>/recording` (the project's recording format,
flushed at least once a second) the moment it happens; `--resume` rebuilds
the replay buffer from it, so `kill -9` loses at most the last second. The
networks resume from the last checkpoint (saved at every evaluation).

Evaluations run on the robot too: `eval_episodes` episodes of the
deterministic actor every `eval_every` robot steps. Their steps are recorded
and learned from like the others; `steps` counts every control step the
robot made.

`init_from` starts the networks from a saved model (a simulation run's):
the robot acts with its stochastic actor from the first step, with no
uniform random actions before `learning_starts`. `safety_budget` has the
learner price each step's safety violations with a multiplier that moves
at the end of every training episode (`robel_dm.learning.safety`).
"""

from collections.abc import Callable
import dataclasses
import json
import pathlib
import time
from typing import Any

import numpy as np

from robel_dm import policies, recording, suite
from robel_dm.hardware import resets
from robel_dm.hardware.dynamixel import errors as dynamixel_errors
from robel_dm.hardware.tracking import tracker as tracking
from robel_dm.learning import agents, demos, run_files
from robel_dm.learning import learner as learner_lib
from robel_dm.learning import training as train_lib
from robel_dm.learning.robot_options import RobotRunOptions
from robel_dm.tasks import base

SAFETY_FIELDS = base.SAFETY_FIELDS
RECORDING = 'recording'
PROGRESS_LOG = 'progress.jsonl'
ROBOT = 'robot.json'
# Errors of the robot an episode survives (after a reset).
FAULTS = (
  dynamixel_errors.DynamixelError,
  tracking.TrackingError,
  resets.ResetError,
)
# Agents that can learn on a robot: off-policy ones learn while it moves;
# behaviour cloning learns from data and is evaluated on it.
ROBOT_AGENTS = ('sac', 'droq', 'sac_demos', 'bc')
# The learner's value of a safety budget's multiplier.
_MULTIPLIER = 'train/safety_multiplier'
# A robot run's budget of safety violations per episode (all kinds summed)
# unless it names a budget or a penalty: the constrained agent's.
ROBOT_SAFETY_BUDGET = agents.get('sac_safe').safety_budget


# --- The actor -------------------------------------------------------------


@dataclasses.dataclass
class _Episode:
  """What one episode did."""

  purpose: str
  steps: int = 0
  reward: float = 0.0
  success: bool = False
  score_total: float = 0.0
  final_score: float = 0.0
  violations: np.ndarray = dataclasses.field(
    default_factory=lambda: np.zeros(3)
  )
  ended: str = 'time limit'

  @property
  def score(self) -> float:
    """ROBEL's score averaged over the episode's steps, as in simulation
    (`evaluation.episodes`); 0 for an episode without steps."""
    return self.score_total / self.steps if self.steps else 0.0


class _RobotRun:
  """The actor side of a run: the robot, the recording, the bookkeeping."""

  def __init__(self, config, options, output, metadata, learner, run):
    self.config, self.options, self.output = config, options, output
    self.metadata, self.learner = metadata, learner
    self.log, self.telemetry = run.log, run.telemetry
    self.steps = 0
    self.episodes = 0
    self.faults = 0
    self.early_ends = 0
    # The robot's time in earlier sessions of the run, s (see robot_seconds).
    self.seconds_before = 0.0
    self._clock_start = 0.0
    # The learner's updates and the time at the previous episode's end.
    self._last_updates = (0, time.monotonic())
    self.rng = np.random.default_rng()
    self.env = None
    self.learning_starts = int(
      config.agent.hyperparameters.get('learning_starts', 0)
    )
    # Networks loaded from --init_from act from the first step: no random
    # actions on a robot before learning starts.
    self.warm = config.init_from is not None

  def open(self, seed: int) -> None:
    env = self.options.load(self.config, seed)
    try:
      self.env = recording.Recorder(
        env,
        self.output / RECORDING,
        metadata={
          'domain': self.config.domain,
          'task': self.config.task,
          'task_kwargs': dict(self.config.task_kwargs),
          'seed': seed,
          'device_path': self.options.robot.device_path,
          'policy': f'train --algo={self.config.algo}',
        },
      )
    except BaseException:
      env.close()
      raise
    self.timing = getattr(self.env.physics, 'timing', None)
    self._clock_start = self.env.physics.clock.now()

  def robot_seconds(self) -> float:
    """The robot's time the run has used, s, resets and evaluations
    included, over every session: its clock's (simulated time on the
    in-process virtual bus, wall time on a robot)."""
    if self.env is None:
      return self.seconds_before
    return (
      self.seconds_before + self.env.physics.clock.now() - self._clock_start
    )

  def resume_counters(self, progress: pathlib.Path) -> None:
    """Continues the faults, early ends and robot time of earlier
    sessions, from the run's progress log."""
    if not progress.is_file():
      return
    lines = progress.read_text().splitlines()
    if not lines:
      return
    last = json.loads(lines[-1])
    self.faults = last.get('faults', 0)
    self.early_ends = last.get('early_ends', 0)
    self.seconds_before = last.get('robot_seconds', 0.0)

  def close(self) -> None:
    if self.env is not None:
      self.env.close()  # Finishes the recording; the motors are released.

  def _reset(self):
    """Resets the robot, retrying; raises after `reset_attempts` failures."""
    for attempt in range(1, self.options.reset_attempts + 1):
      try:
        return self.env.reset()
      except FAULTS as error:
        self.faults += 1
        self.log(
          f'reset failed ({attempt} of {self.options.reset_attempts}): '
          f'{type(error).__name__}: {error}'
        )
        last = error
    raise RuntimeError(
      f'the robot could not be reset {self.options.reset_attempts} times in '
      f'a row (last: {last}); the run is saved: fix the robot, then --resume'
    ) from last

  def episode(self, purpose: str, policy=None) -> _Episode:
    """One episode: training (the stochastic actor, or uniform actions
    before learning starts unless the networks were loaded) or evaluation
    (`policy`, deterministic). A training episode that made a step tells
    the learner its violations in all (a safety budget's multiplier moves
    by them)."""
    self.env.annotate(purpose=purpose)
    timestep = self._reset()
    result = _Episode(purpose)
    since = len(self.timing) if self.timing is not None else 0
    flatten = self.env.task.flatten_observation
    observation = flatten(timestep.observation).astype(np.float32)
    action_size = self.env.action_spec().shape[0]
    while not timestep.last():
      self.learner.poll()
      if policy is not None:
        action = policy.act(observation)
      elif self.learner.actor is None or (
        self.steps < self.learning_starts and not self.warm
      ):
        action = self.rng.uniform(-1.0, 1.0, action_size)
      else:
        action = self.learner.actor.sample(observation, self.rng)
      try:
        timestep = self.env.step(action)
      except FAULTS as error:
        self.faults += 1
        result.ended = f'fault: {type(error).__name__}: {error}'
        self.log(f'hardware fault, episode ended, torque off: {error}')
        break
      next_observation = flatten(timestep.observation).astype(np.float32)
      terminal = timestep.last() and timestep.discount == 0.0
      safety = timestep.observation['safety']
      # What the agent learns from (--safety_penalty); the logs keep
      # ROBEL's reward.
      reward = timestep.reward - self.config.safety_penalty * safety.sum()
      self.learner.add(
        demos.Transitions(
          observations=observation[None],
          actions=np.asarray(action, np.float32)[None],
          rewards=np.float32([reward]),
          next_observations=next_observation[None],
          terminals=np.array([terminal]),
          episodes=0,
          violations=np.float32([safety.sum()]),
        )
      )
      if self.options.paced_by_learner:
        self.learner.wait_until_caught_up()
      observation = next_observation
      self.steps += 1
      result.steps += 1
      result.reward += float(timestep.reward)
      result.violations += safety
      result.success = bool(timestep.observation['success'])
      result.final_score = float(timestep.observation['score'])
      result.score_total += result.final_score
      limit = self.options.max_violations
      if limit is not None and result.violations.sum() >= limit:
        result.ended = f'safety: {int(result.violations.sum())} violations'
        self.early_ends += 1
        break
    else:
      if timestep.discount == 0.0:
        result.ended = 'task ended it'
    if policy is None and result.steps:  # Cut short or not.
      self.learner.end_episode(float(result.violations.sum()))
    self.episodes += 1
    self._progress(result, since)
    return result

  def _progress(self, result: _Episode, since: int) -> None:
    timing = self.timing.summary(since) if self.timing is not None else None
    row = {
      'episode': self.episodes,
      'purpose': result.purpose,
      'robot_steps': self.steps,
      'steps': result.steps,
      'return': result.reward,
      'success': result.success,
      'score': result.score,
      'final_score': result.final_score,
      'violations': dict(
        zip(SAFETY_FIELDS, result.violations.tolist(), strict=True)
      ),
      'ended': result.ended,
      'updates': self.learner.updates,
      'robot_seconds': self.robot_seconds(),
      'faults': self.faults,
      'early_ends': self.early_ends,
      'timing': None if timing is None else dataclasses.asdict(timing),
    }
    # Under a safety budget: the latest multiplier the learner sent.
    multiplier = getattr(self.learner, 'values', {}).get(_MULTIPLIER)
    if multiplier is not None:
      row['safety_multiplier'] = multiplier
    with open(self.output / PROGRESS_LOG, 'a') as file:
      file.write(json.dumps(row) + '\n')
    self._scalars(result, timing)
    violations = '/'.join(f'{v:.0f}' for v in result.violations)
    self.log(
      f'episode {self.episodes} ({result.purpose}): {result.steps} steps, '
      f'return {result.reward:.1f}, success {int(result.success)}, '
      f'violations pos/vel/cur {violations}, {result.ended}'
      + (f'; {timing.line()}' if timing is not None else '')
      + f' | robot steps {self.steps}, updates {self.learner.updates}, '
      f'faults {self.faults}'
      + ('' if multiplier is None else f', multiplier {multiplier:.3g}')
    )

  def _scalars(self, result: _Episode, timing) -> None:
    """The episode's and the run's robot values, to TensorBoard."""
    updates, now = self.learner.updates, time.monotonic()
    last_updates, last_time = self._last_updates
    self._last_updates = (updates, now)
    learned = max(self.steps - self.learning_starts, 1)
    values = {
      **getattr(self.learner, 'values', {}),
      'robot/return': result.reward,
      'robot/success': float(result.success),
      'robot/faults': self.faults,
      'robot/early_ends': self.early_ends,
      'robot/resets': self.episodes,
      'robot/updates_per_step': updates / learned,
      'robot/updates_per_second': (updates - last_updates)
      / max(now - last_time, 1e-9),
      'robot/seconds': self.robot_seconds(),
    }
    for kind, value in zip(SAFETY_FIELDS, result.violations, strict=True):
      values[f'robot/violations_{kind}'] = float(value)
    if timing is not None:
      values['robot/jitter_p50_ms'] = timing.jitter_p50 * 1e3
      values['robot/jitter_p99_ms'] = timing.jitter_p99 * 1e3
      values['robot/late_steps'] = timing.late_steps
    since = getattr(self.learner, 'actor_since', 0.0)
    if since:
      values['robot/actor_age_s'] = now - since
    # An episode too short to time (a fault at its first step) has none.
    finite = {tag: v for tag, v in values.items() if np.isfinite(v)}
    self.telemetry.scalars(finite, self.steps)

  def evaluate(self, policy: policies.NumpyPolicy) -> dict[str, Any]:
    """The evaluation metrics of `policy`, from episodes on the robot."""
    episodes = [
      self.episode('evaluation', policy)
      for _ in range(self.config.eval_episodes)
    ]
    n = len(episodes)
    violations = sum(e.violations for e in episodes) / n
    return {
      'success_rate': sum(e.success for e in episodes) / n,
      'mean_score': sum(e.score for e in episodes) / n,
      'mean_final_score': sum(e.final_score for e in episodes) / n,
      'mean_return': sum(e.reward for e in episodes) / n,
      'safety': dict(zip(SAFETY_FIELDS, violations.tolist(), strict=True)),
      'episodes': n,
      'on_robot': True,
      'robot_seconds': self.robot_seconds(),
    }


def _recorded(output: pathlib.Path, config, keys) -> demos.Transitions | None:
  """Every transition the run's recording holds (None if it has none)."""
  directory = output / RECORDING
  if not (directory / 'meta').is_dir():
    return None
  if not any(len(episode) > 1 for episode in recording.read(directory)):
    return None  # Killed before its first step was flushed.
  return demos.load(
    directory,
    config.domain,
    config.task,
    keys,
    config.task_kwargs,
    complete_only=False,
  )


def with_safe_defaults(config: train_lib.RunConfig) -> train_lib.RunConfig:
  """`config` as `train --device_path` takes it by default: acting through
  the safe action map unless its task arguments name a map, and, for a
  SAC agent with neither a safety budget nor a penalty, learning under
  ROBOT_SAFETY_BUDGET violations per episode."""
  changes: dict[str, Any] = {
    'task_kwargs': {'action_map': 'safe', **config.task_kwargs}
  }
  if (
    config.agent.library == agents.SAC_JAX
    and config.safety_budget is None
    and not config.safety_penalty
  ):
    changes['safety_budget'] = ROBOT_SAFETY_BUDGET
  return dataclasses.replace(config, **changes)


def train_on_robot(
  config: train_lib.RunConfig,
  options: RobotRunOptions,
  output_dir: str | pathlib.Path,
  *,
  resume: bool = False,
  overwrite: bool = False,
  log: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
  """Trains `config` on a robot in real time (see the module docstring).
  `overwrite` starts over in an `output_dir` that holds a run.

  Returns:
    The evaluation log.

  Raises:
    ValueError: for bad settings or a --resume with other ones, before the
      robot moves.
    RuntimeError: when the robot cannot be reset (the run is saved).
  """
  _check_settings(config, options)
  metadata = train_lib.metadata_of(config)
  keys = tuple(metadata['observation_keys'])
  output = pathlib.Path(output_dir)
  data, recorded = _prepare_output_dir(
    config, options, output, keys, resume=resume, overwrite=overwrite
  )
  (output / train_lib.METADATA).write_text(json.dumps(metadata, indent=1))
  run = train_lib.Run(output, config, log)
  if resume:
    run.load_history()
  else:
    run.log_path.write_text('')
  if config.agent.kind == agents.IMITATION:
    policy = _cloned_policy(config, data, metadata)
    _evaluate_on_robot(config, options, output, run, policy, metadata, log)
  else:
    _learn_on_robot(config, options, run, metadata, data, recorded, resume)
  return run.history


def _check_settings(
  config: train_lib.RunConfig, options: RobotRunOptions
) -> None:
  """Raises ValueError for settings a robot run cannot use."""
  config.check()
  options.check()
  if config.algo not in ROBOT_AGENTS:
    raise ValueError(
      f'on a robot --algo must be one of {", ".join(ROBOT_AGENTS)}, '
      f'got {config.algo}'
    )
  if config.num_envs != 1:
    raise ValueError('a robot is one environment: --num_envs must be 1')
  if config.task_kwargs.get('privileged'):
    raise ValueError(
      'privileged observations are what only a simulation knows: a robot '
      'gives none'
    )
  if (
    config.init_from is not None
    and not (
      run_files.init_checkpoint(config.init_from).parent / run_files.CONFIG
    ).is_file()
  ):
    raise ValueError(
      f'--init_from={config.init_from}: no {run_files.CONFIG} beside the '
      'model, so its action map and valve cannot be checked against this '
      'run: give its run folder'
    )
  # The learner process imports the agent's library; the actor need not.
  agents.check_available(config.agent)


def _prepare_output_dir(
  config: train_lib.RunConfig,
  options: RobotRunOptions,
  output: pathlib.Path,
  keys: tuple[str, ...],
  *,
  resume: bool,
  overwrite: bool,
) -> tuple[demos.Transitions | None, demos.Transitions | None]:
  """Checks `output` (and a resumed run's settings), loads the
  demonstrations and a resumed run's recording, then (only then) clears an
  overwritten run and writes the settings.

  Returns:
    The demonstrations and the recorded transitions, each None if none.
  """
  robot_files = (RECORDING, PROGRESS_LOG, ROBOT)
  train_lib.check_output_dir(
    output, resume, overwrite, run_files.RUN_MARKERS + robot_files
  )
  if resume:
    train_lib.check_resume(output, config, need_checkpoint=False)
    options.check_resume(output / ROBOT)
  data = train_lib.load_data(config, keys)
  recorded = _recorded(output, config, keys) if resume else None
  if overwrite:  # After every check: a refused run removes nothing.
    train_lib.clear_output_dir(output, run_files.RUN_FILES + robot_files)
  output.mkdir(parents=True, exist_ok=True)
  (output / train_lib.CONFIG).write_text(json.dumps(config.to_json(), indent=1))
  (output / ROBOT).write_text(json.dumps(options.to_json(), indent=1))
  return data, recorded


def _cloned_policy(config: train_lib.RunConfig, data, metadata):
  """Behaviour cloning's policy, fitted to the demonstrations `data`."""
  from robel_dm.learning import imitation  # noqa: PLC0415

  hyper = config.agent.hyperparameters
  fit_config = imitation.FitConfig(
    hidden=config.layers,
    seed=config.seed,
    epochs=config.steps,
    batch_size=hyper['batch_size'],
    learning_rate=hyper['learning_rate'],
  )
  return imitation.fit_policy(data, fit_config, metadata)


def _learn_on_robot(
  config, options, run, metadata, data, recorded, resume: bool
) -> None:
  """Runs the learner process and the robot until the run ends, then
  releases the robot first, stops the learner and finishes the run."""
  output = run.output
  held = sum(len(d) for d in (data, recorded) if d is not None)
  observation_size, action_size = _sizes(
    config, tuple(metadata['observation_keys'])
  )
  setup = learner_lib.LearnerSetup(
    algo=config.algo,
    seed=config.seed,
    layers=config.layers,
    observation_size=observation_size,
    action_size=action_size,
    # Room for the evaluations' and the last episode's steps too, which
    # may run past `steps`; beyond that the oldest transitions go first.
    buffer_size=2 * config.steps + held,
    checkpoint=str(output / train_lib.CHECKPOINT),
    resume=resume,
    updates_per_step=options.updates_per_step
    or agents.updates_per_step(config.agent),
    init_from=config.init_from,
    safety_budget=config.budget,
  )
  learner = learner_lib.Learner(setup)
  actor = _RobotRun(config, options, output, metadata, learner, run)
  try:
    for batch in (data, recorded):
      if batch is not None:
        learner.add(batch)
    if recorded is not None:
      actor.steps = len(recorded)
      actor.episodes = recorded.episodes
      actor.resume_counters(output / PROGRESS_LOG)
      run.log(
        f'resuming at robot step {actor.steps}: {len(recorded)} recorded '
        'transitions back in the replay buffer'
      )
    _actor_loop(config, options, run, actor, learner, metadata)
  finally:
    try:
      actor.close()  # The robot first: torque off before anything else.
    finally:
      try:
        learner.close()
      finally:
        _finish(run, config, output)


def _finish(run: train_lib.Run, config, output: pathlib.Path) -> None:
  """Closes the run's TensorBoard file and draws its learning curve (also
  after Ctrl-C or a fault that stopped it)."""
  from robel_dm.learning import curves  # noqa: PLC0415

  run.close()
  curves.plot_run(
    run.log_path,
    output / train_lib.CURVE,
    f'{config.domain}/{config.task} ({config.algo}, seed {config.seed}) '
    'on a robot',
  )


def _sizes(config, keys: tuple[str, ...]) -> tuple[int, int]:
  """The agent vector's and the action's sizes (from the simulation)."""
  env = suite.load(config.domain, config.task, task_kwargs=config.task_kwargs)
  spec = env.observation_spec()
  size = sum(int(np.prod(spec[key].shape)) for key in keys)
  actions = env.action_spec().shape[0]
  env.close()
  return size, actions


def _actor_loop(config, options, run, actor, learner, metadata) -> None:
  deadline = time.monotonic() + options.hours * 3600 if options.hours else None
  if actor.warm or actor.steps >= actor.learning_starts:
    # A resumed run acts with its restored networks from its first step,
    # and a run --init_from with the loaded ones, not with random actions
    # while the learner loads them; a model that does not fit the task
    # fails here, before the robot is opened.
    learner.wait_for_actor()
  # A new stream of episodes per session: a resumed run does not replay
  # the goals it has already seen.
  actor.open(config.seed * 1000 + actor.episodes)
  actor.rng = np.random.default_rng([config.seed, actor.steps])
  run.start_clocks()

  def evaluate_now() -> bool:
    learner.request('save')
    policy = learner.wait_for_actor().numpy_policy(metadata)
    row = run.record(policy, actor.steps, evaluator=actor.evaluate)
    return run.solved(row)

  # The evaluation after the last one logged: one cut short by a kill (its
  # steps recorded, its row not) is made again at once.
  next_eval = (
    (run.history[-1]['env_steps'] // config.eval_every + 1) * config.eval_every
    if run.history
    else 0
  )
  while actor.steps < config.steps:
    if deadline is not None and time.monotonic() > deadline:
      run.log(f'--hours budget used at robot step {actor.steps}; saved')
      break
    learner.check_alive()
    if actor.steps >= next_eval:
      if evaluate_now():
        break
      next_eval = (actor.steps // config.eval_every + 1) * config.eval_every
      continue
    actor.episode('training')
  else:
    evaluate_now()


def _evaluate_on_robot(config, options, output, run, policy, metadata, log):
  """Behaviour cloning on a robot: the robot only evaluates."""

  class _NoLearner:
    updates = 0
    actor = None

    def poll(self):
      pass

    def add(self, batch):
      pass

    def end_episode(self, violations):
      pass

    def wait_until_caught_up(self):
      pass

  actor = _RobotRun(config, options, output, metadata, _NoLearner(), run)
  try:
    actor.open(config.seed * 1000)
    run.start_clocks()
    run.record(policy, 0, evaluator=actor.evaluate, epoch=config.steps)
  finally:
    try:
      actor.close()
    finally:
      _finish(run, config, output)
