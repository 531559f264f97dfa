"""Evaluates a policy on a robel_dm task with ROBEL's metrics.

    from robel_dm import evaluation

    results = evaluation.evaluate(
      evaluation.EvalConfig('dclaw', 'pose_fixed', 20, policy='reference')
    )

The results hold the success rate (ROBEL's success evaluator: the `success`
signal at each episode's last step), mean return, mean score, mean safety
violations per episode and the control steps per second, with one record
per episode. `robel-evaluate` is the command over it
(`evaluation.cli`); `episodes` runs the episodes one after another,
`workers` on local processes or a Ray cluster.
"""

from collections.abc import Callable, Sequence
import dataclasses
from typing import Any

from robel_dm import policies, provenance, recording, suite
from robel_dm.environment import Environment
from robel_dm.evaluation import episodes, workers


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  """What an evaluation runs, and how (checked when made).

  Episode i starts from a reset seeded with `seed + i` (the `random`
  policy's actions from that seed too), so any episode can be reproduced on
  its own.

  Attributes:
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

  Raises:
    ValueError: when made with bad options (episodes < 1, workers < 1,
      video episodes outside the run or without a video folder, workers
      or Ray with what only a serial run can do).
  """

  domain: str
  task: str
  episodes: int
  policy: str | policies.Policy = 'random'
  seed: int | None = 0
  task_kwargs: dict[str, Any] | None = None
  log_every: int = 0
  robot: suite.RobotOptions | None = None
  on_episode: Callable[[dict[str, Any]], None] | None = None
  video_dir: str | None = None
  camera: str | None = None
  workers: int = 1
  ray_address: str | None = None
  record: str | None = None
  dynamics: str | None = None
  allow_other_seed: bool = False
  video_episodes: Sequence[int] | None = None
  log: Callable[[str], None] | None = None

  def __post_init__(self):
    if self.episodes < 1:
      raise ValueError(f'episodes must be >= 1, got {self.episodes}')
    if self.video_episodes is not None:
      outside = sorted(set(self.video_episodes) - set(range(self.episodes)))
      if outside:
        raise ValueError(
          f'video episodes {outside} are not among the {self.episodes} '
          f'episodes (0..{self.episodes - 1})'
        )
      if self.video_dir is None:
        raise ValueError('video episodes need a video folder (--video=DIR)')
    if self.workers < 1:
      raise ValueError(f'workers must be >= 1, got {self.workers}')
    if self.distributed:
      self._check_distributed()

  def _check_distributed(self) -> None:
    """Raises ValueError naming the first option that workers (or a Ray
    cluster) cannot share."""
    for conflict, reason in (
      (self.replay, 'a replay (each worker would replay from its start)'),
      (self.robot, 'a robot (one process owns it)'),
      (self.video_dir, 'video (one process films)'),
      (self.record, 'recording (one process records)'),
      (self.dynamics, 'dynamics (a calibration)'),
      (self.seed is None, 'an unseeded run (the workers need a seed)'),
      (
        callable(self.policy),
        'a policy given as an object (give it by name or path; not with '
        '--allow_other_variant)',
      ),
    ):
      if conflict:
        raise ValueError(f'--workers / --ray_address: not with {reason}')

  @property
  def replay(self) -> bool:
    """Whether the policy replays a recording ('replay:DIR')."""
    return isinstance(self.policy, str) and self.policy.startswith(
      policies.REPLAY
    )

  @property
  def distributed(self) -> bool:
    """Whether the episodes run on workers or Ray, not in this process."""
    return self.workers > 1 or bool(self.ray_address)

  @property
  def policy_name(self) -> str:
    """The policy as the results name it."""
    return self.policy if isinstance(self.policy, str) else repr(self.policy)


def evaluate(
  config: EvalConfig,
  *,
  env: Environment | None = None,
  provenance_record: dict[str, Any] | None = None,
) -> dict[str, Any]:
  """Runs the episodes of `config` and returns the metrics.

  Args:
    config: what to run, and how.
    env: a simulated environment of `config`'s task to run the episodes
      in, for a caller that evaluates many policies (training): built by
      the caller, left open. Every episode starts from a seeded reset, so
      the records equal those of a new environment. None builds one.
    provenance_record: the provenance the results carry, for a caller that
      read it once (`provenance.describe()`) for many evaluations; None
      reads it.

  Returns:
    A JSON-serializable dict of per-episode records, summary metrics,
    spreads and provenance (software versions, git revision, time,
    machine).

  Raises:
    ValueError: for bad arguments (unknown task or policy, or an `env`
      with what needs an environment of its own).
  """
  if env is not None and (
    config.distributed or config.robot or config.record or config.dynamics
  ):
    raise ValueError(
      'a given env runs simulated episodes here: no workers, Ray, robot, '
      'recording or dynamics'
    )
  # A policy file is read and checked against the task before anything is
  # built (and a robot moves); None for policies that are not files.
  checked = _checked_policy(config)
  config = _with_policy_task_options(config, checked)
  if env is not None:
    tally = episodes.Tally(_head(config, provenance_record), config.on_episode)
    _run_here(config, env, _policy(config, env, checked), tally)
    return tally.results()
  env = suite.load(
    config.domain,
    config.task,
    seed=config.seed,
    task_kwargs=config.task_kwargs,
    robot=config.robot,
    dynamics=config.dynamics,
  )
  if config.record is not None:
    env = _recorder(env, config)
  tally = episodes.Tally(_head(config, provenance_record), config.on_episode)
  try:
    act = _policy(config, env, checked)
    if config.distributed:
      env.close()
      _run_on_workers(config, tally)
    else:
      _run_here(config, env, act, tally)
  finally:
    env.close()
  return tally.results()


def _checked_policy(config: EvalConfig) -> policies.Policy | None:
  """The policy of a policy file or a replay, read and checked before
  anything is built, or a loaded policy file given as such; None for the
  other policies."""
  if isinstance(config.policy, policies.NumpyPolicy):
    # Loaded by the caller (e.g. for another variant): it still acts
    # through its own action map, on its own observation.
    return config.policy
  checked = policies.check_file(
    config.policy, config.domain, config.task, config.task_kwargs
  )
  if config.replay:
    checked = policies.ReplayPolicy(
      config.policy[len(policies.REPLAY) :], config.domain, config.task,
      config.task_kwargs, config.seed, episodes=config.episodes,
      check_seed=not config.allow_other_seed,
    )  # fmt: skip
  return checked


def _with_policy_task_options(
  config: EvalConfig, checked: policies.Policy | None
) -> EvalConfig:
  """`config` with the checked policy file's action map (if it learned
  through another than ROBEL's) and privileged observation (if it reads
  it), where the task arguments name none (said in the log)."""
  task_kwargs_for = getattr(checked, 'task_kwargs_for', None)
  if task_kwargs_for is None:
    return config
  task_kwargs = task_kwargs_for(config.task_kwargs, config.log, 'evaluating')
  if task_kwargs == dict(config.task_kwargs or {}):
    return config
  return dataclasses.replace(config, task_kwargs=task_kwargs)


def _recorder(env, config: EvalConfig) -> recording.Recorder:
  """`env` recorded into `config.record` (closed if that fails)."""
  try:
    return recording.Recorder(
      env,
      config.record,
      metadata=_settings(config),
    )
  except recording.RecordingError:
    env.close()
    raise


def _settings(config: EvalConfig) -> dict[str, Any]:
  """The run's settings, as its results and its recording name them."""
  return {
    'domain': config.domain,
    'task': config.task,
    'task_kwargs': config.task_kwargs or {},
    'policy': config.policy_name,
    'seed': config.seed,
    'device_path': config.robot and config.robot.device_path,
    'dynamics': config.dynamics,
  }


def _head(
  config: EvalConfig, provenance_record: dict[str, Any] | None
) -> dict[str, Any]:
  """What the results start with: the run's settings and provenance."""
  return {
    **_settings(config),
    'episodes_requested': config.episodes,
    'provenance': provenance_record or provenance.describe(),
  }


def _policy(
  config: EvalConfig, env, checked: policies.Policy | None
) -> policies.Policy:
  """The policy that acts in `env` (a callable is checked against the
  task, a name is built)."""
  policy = config.policy
  if callable(policy):
    if isinstance(policy, policies.NumpyPolicy):
      policy.check_task(config.domain, config.task, config.task_kwargs)
    return policy
  if checked is not None:
    return checked
  return policies.make_policy(
    policy, env, config.seed, config.domain, config.task, config.task_kwargs
  )


def _run_on_workers(config: EvalConfig, tally: episodes.Tally) -> None:
  """The episodes on local worker processes or Ray tasks, into `tally`."""
  run = workers.ray_episodes if config.ray_address else workers.local_episodes
  for record, steps, seconds in run(
    config.domain, config.task, config.task_kwargs, config.policy,
    config.seed, config.episodes, config.ray_address or config.workers,
  ):  # fmt: skip
    tally.add(record, steps, seconds)


def _run_here(
  config: EvalConfig, env, act: policies.Policy, tally: episodes.Tally
) -> None:
  """The episodes one after another in `env` (filmed as asked), into
  `tally`."""
  films = None
  if config.video_dir is not None:
    filmed = (
      range(config.episodes)
      if config.video_episodes is None
      else config.video_episodes
    )
    films = episodes.open_films(
      env,
      episodes.Films(
        config.video_dir,
        config.camera,
        frozenset(filmed),
        config.domain,
        config.task,
      ),
      config.log,
    )

  def act_for(episode_seed: int | None) -> policies.Policy:
    if config.policy == 'random':  # Each episode's actions from its seed.
      return policies.make_policy('random', env, episode_seed)
    return act

  seed = config.seed
  seeds = [None if seed is None else seed + i for i in range(config.episodes)]
  episodes.run_serial(env, act_for, seeds, tally, films, config.log_every)
