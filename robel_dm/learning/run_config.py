"""What a training run is: `RunConfig`, checked before anything runs."""

from collections.abc import Sequence
import dataclasses
import json
import pathlib
from typing import Any

import numpy as np

from robel_dm import suite
from robel_dm.learning import agents, run_files
from robel_dm.tasks import base

# What --resume may change: the budget and how often it is evaluated.
RESUMABLE_CHANGES = (
  'steps',
  'eval_every',
  'eval_episodes',
  'stop_at_success',
  'stop_streak',
)


# The agents that take a safety budget and start from another run.
_SBX_SAC = tuple(
  sorted(
    name for name, a in agents.AGENTS.items() if a.library == agents.SAC_JAX
  )
)


@dataclasses.dataclass(frozen=True)
class RunConfig:
  """What a training run is.

  Attributes:
    domain: 'dclaw' or 'dkitty'.
    task: the task, e.g. 'turn_fixed'.
    task_kwargs: the task's arguments (e.g. {'valve': 'valve4'}).
    algo: an agent of `agents.AGENTS`.
    seed: seeds the agent and the training episodes.
    steps: env steps to train for (epochs for `bc`).
    num_envs: environments stepped together.
    eval_every: env steps (epochs for `bc`) between evaluations.
    eval_episodes: episodes per evaluation.
    safety_penalty: the training reward minus this per safety violation.
    safety_budget: learn to keep safety violations per episode (all kinds
      summed) under this many, with a learned price per violation (a
      Lagrange multiplier; SAC agents only); None: no budget.
    hidden: hidden layer sizes; the agent's own if empty.
    demos: recording directories of demonstrations (bc, sac_demos).
    demo_episodes: how many demonstration episodes to use.
    stop_at_success: end the run early once `stop_streak` evaluations in a
      row reach this success rate (never if None).
    stop_streak: see `stop_at_success`.
    from_recording: recordings (of this task, simulated or on a robot,
      complete episodes or not) whose every transition starts the replay
      buffer of an off-policy agent, or joins behaviour cloning's data.
    init_from: a run folder (or its checkpoint.zip) of the same agent on
      a task with the same observations and actions, e.g. the Random
      variant: the run starts from its networks (SAC agents only), with a
      replay buffer of its own.
  """

  domain: str
  task: str
  task_kwargs: dict[str, Any] = dataclasses.field(default_factory=dict)
  algo: str = agents.DEFAULT
  seed: int = 0
  steps: int = 30_000
  num_envs: int = 1
  eval_every: int = 5_000
  eval_episodes: int = 10
  safety_penalty: float = 0.0
  safety_budget: float | None = None
  hidden: tuple[int, ...] = ()
  demos: tuple[str, ...] = ()
  demo_episodes: int = 20
  stop_at_success: float | None = None
  stop_streak: int = 1
  from_recording: tuple[str, ...] = ()
  init_from: str | None = None

  @property
  def agent(self) -> agents.Agent:
    return agents.get(self.algo)

  @property
  def budget(self) -> float | None:
    """The safety budget: this run's, else its agent's."""
    if self.safety_budget is not None:
      return self.safety_budget
    return self.agent.safety_budget

  @property
  def policy_task_kwargs(self) -> dict[str, Any]:
    """The task's arguments as the policy sees the task (evaluations, the
    saved policy): with the privileged observation if its agent's actor
    observes it."""
    agent = self.agent
    if agent.privileged == agents.PRIVILEGED_ACTOR:
      return {**self.task_kwargs, 'privileged': agent.privileged_view}
    return dict(self.task_kwargs)

  @property
  def training_task_kwargs(self) -> dict[str, Any]:
    """The task's arguments as training sees it: with the privileged
    observation if its agent's actor or critics observe it."""
    agent = self.agent
    if agent.privileged is not None:
      return {**self.task_kwargs, 'privileged': agent.privileged_view}
    return dict(self.task_kwargs)

  @property
  def layers(self) -> tuple[int, ...]:
    return tuple(self.hidden) or self.agent.hidden

  def check(self) -> None:
    """Raises ValueError naming the first bad setting."""
    self._check_numbers()
    self._check_sac_options()
    if any(size < 1 for size in self.layers):
      raise ValueError(f'hidden sizes must be >= 1, got {self.hidden}')
    self._check_data()
    self._check_imitation()
    randomized = (self.domain, self.task) in suite.RANDOM_DYNAMICS
    agent = self.agent
    if agent.starts_from is not None and self.init_from is None:
      raise ValueError(
        f'--algo={self.algo} starts from another run: give --init_from=RUN '
        '(without it, it is the agent it is made from)'
      )
    if (agent.privileged or agent.curriculum) and not randomized:
      raise ValueError(
        f'--algo={self.algo} works on the randomized dynamics: it needs a '
        f'RandomDynamics task, not {self.domain}/{self.task}'
      )

  def _check_numbers(self) -> None:
    """Counts, seed, penalty and stop rate in range."""
    for name in (
      'steps',
      'num_envs',
      'eval_every',
      'eval_episodes',
      'stop_streak',
      'demo_episodes',
    ):
      if getattr(self, name) < 1:
        raise ValueError(f'{name} must be >= 1, got {getattr(self, name)}')
    if self.safety_penalty < 0 or not np.isfinite(self.safety_penalty):
      raise ValueError(
        f'safety_penalty must be >= 0, got {self.safety_penalty}'
      )
    if self.seed < 0:
      raise ValueError(f'seed must be >= 0, got {self.seed}')
    if self.stop_at_success is not None and not (
      0 <= self.stop_at_success <= 1
    ):
      raise ValueError(
        f'stop_at_success is a success rate in [0, 1], got '
        f'{self.stop_at_success}'
      )

  def _check_data(self) -> None:
    """Demonstrations and recordings: where the agent can use them."""
    agent = self.agent
    if agent.needs_demos and not (self.demos or self.from_recording):
      raise ValueError(f'--algo={self.algo} learns from --demos=DIR')
    if self.from_recording and agent.kind == agents.ON_POLICY:
      raise ValueError(
        f'--algo={self.algo} learns on-policy: it cannot start from '
        '--from_recording'
      )
    if self.demos and not agent.needs_demos:
      raise ValueError(f'--algo={self.algo} does not use --demos')
    if (self.demos or self.from_recording) and self.num_envs != 1:
      raise ValueError('demonstrations and recordings need --num_envs=1')

  def _check_imitation(self) -> None:
    """Raises ValueError for a setting behaviour cloning would ignore."""
    if self.agent.kind != agents.IMITATION:
      return
    for name, given in (
      ('stop_at_success', self.stop_at_success is not None),
      ('safety_penalty', bool(self.safety_penalty)),
      ('num_envs', self.num_envs != 1),
    ):
      if given:
        raise ValueError(
          f'--{name}: --algo={self.algo} fits demonstrations for --steps '
          'epochs, in no environment'
        )

  def _check_sac_options(self) -> None:
    sac_agent = self.agent.library == agents.SAC_JAX
    if self.safety_budget is not None:
      if not (self.safety_budget >= 0 and np.isfinite(self.safety_budget)):
        raise ValueError(
          f'safety_budget must be >= 0, got {self.safety_budget}'
        )
      if self.safety_penalty:
        raise ValueError(
          'choose one of safety_penalty (a fixed price per violation) and '
          'safety_budget (a learned one)'
        )
    for name in ('safety_budget', 'init_from'):
      if getattr(self, name) is not None and not sac_agent:
        raise ValueError(
          f'--{name} needs an sbx SAC agent ({", ".join(_SBX_SAC)}), not '
          f'--algo={self.algo}'
        )
    if self.init_from is not None:
      checkpoint = run_files.init_checkpoint(self.init_from)
      if not checkpoint.is_file():
        raise ValueError(
          f'--init_from={self.init_from}: no saved model there (a run '
          'folder with checkpoint.zip, or such a file)'
        )
      self._check_source(checkpoint.parent / run_files.CONFIG)

  def _check_source(self, source_config: pathlib.Path) -> None:
    """Raises ValueError if the run that saved an --init_from model (its
    settings, when beside it) built other networks than this run's agent
    builds: loading it would mix the two agents."""
    if not source_config.is_file():
      return  # A bare model file: loading it checks what it can.
    saved = json.loads(source_config.read_text())
    for option, theirs, ours in base.interface_differences(
      saved.get('task_kwargs'), self.task_kwargs
    ):
      raise ValueError(
        f'--init_from={self.init_from} learned with {option} {theirs}, '
        f'this run has {ours} (its networks would mean something else)'
      )
    source = agents.get(saved['algo'])
    hidden = tuple(saved.get('hidden') or source.hidden)
    agent = self.agent
    if (source.library, source.network, hidden) != (
      agent.library,
      agent.network,
      self.layers,
    ):
      raise ValueError(
        f'--init_from={self.init_from} was made by --algo={saved["algo"]} '
        f'(networks {list(hidden)}, {source.network or "plain"}), whose '
        f'networks --algo={self.algo} does not build '
        f'({list(self.layers)}, {agent.network or "plain"}): pass '
        f'--algo={saved["algo"]}'
      )

  def to_json(self) -> dict[str, Any]:
    data = dataclasses.asdict(self)
    data['hidden'] = list(self.layers)
    data['demos'] = list(self.demos)
    data['from_recording'] = list(self.from_recording)
    # What the agent was built with: a resume under other defaults (a newer
    # robel_dm) would otherwise go on with other settings unnoticed.
    data['hyperparameters'] = dict(self.agent.hyperparameters)
    return data

  @classmethod
  def from_json(cls, data: dict[str, Any]) -> 'RunConfig':
    fields = {f.name for f in dataclasses.fields(cls)}
    data = {k: v for k, v in data.items() if k in fields}
    data['hidden'] = tuple(data.get('hidden', ()))
    data['demos'] = tuple(data.get('demos', ()))
    data['from_recording'] = tuple(data.get('from_recording', ()))
    return cls(**data)


def parse_hidden(values: Sequence[str]) -> tuple[int, ...]:
  try:
    return tuple(int(value) for value in values if value)
  except ValueError:
    raise ValueError(
      f'--hidden={",".join(values)}: give layer sizes, e.g. 256,256'
    ) from None
