r"""The baseline table: its runs, how to run them, and its report.

    # Run the table (resumable; one process per core, or a Ray cluster):
    robel-baselines train --queue=0 --queues=2 &
    robel-baselines train --queue=1 --queues=2 &
    robel-baselines train --ray_address=auto
    # One run, or a selection (fnmatch patterns on the run names,
    # comma-separated):
    robel-baselines train --only='dclaw_pose_*'
    # docs/baselines.json, docs/baselines.md's table and one figure per task:
    robel-baselines report

The runs come from `plan.json` (tasks, budgets, seeds, agents). Each run
trains with `robel_dm.learning.training` into `runs/baselines/<name>/`.
Every decision about a run (when it stops, which of its policies it keeps,
which run's policy is shipped) is made on validation episodes; its
reported success is then read once, on test episodes no decision sees
(`PROTOCOL`, docs/baselines.md "How a run is scored"). Demonstrations
(bc, sac_demos) come from `demonstrations`; a run whose demonstrations
cannot be made yet waits for a later pass.
"""

import dataclasses
import fcntl
import fnmatch
import json
import pathlib
import subprocess
from typing import Any

import numpy as np

from robel_dm import suite

ROOT = pathlib.Path(__file__).resolve().parents[3]
PLAN = json.loads((pathlib.Path(__file__).with_name('plan.json')).read_text())
RUNS_DIR = ROOT / 'runs' / 'baselines'
RESULTS = ROOT / 'docs' / 'baselines.json'
DOC = ROOT / 'docs/baselines.md'
README = ROOT / 'README.md'
FIGURES = ROOT / 'docs' / 'baselines'
POLICIES = ROOT / 'policies'
COMMIT = 'commit.txt'
CONFIRMATIONS = 'confirmations.jsonl'
VALIDATION = 'validation.json'
TEST = 'test.json'
# The evaluation protocol of the records (docs/baselines.md "How a run is
# scored"): 1, a final evaluation that could send a run back to training;
# 2, decisions on validation episodes, success read once on test episodes.
PROTOCOL = 2
# Episode seeds of each use, apart from each other and from training's
# (seeds 0-2) and its evaluations' (training.EVAL_SEED_OFFSET).
VALIDATION_SEED_OFFSET = 2_000_000
DEMO_SEED_OFFSET = 4_000_000
CONFIRM_SEED_OFFSET = 6_000_000
TEST_SEED_OFFSET = 9_000_000


@dataclasses.dataclass(frozen=True)
class Run:
  """One run of the table."""

  domain: str
  task: str
  algo: str
  seed: int
  valve4: bool = False

  @property
  def name(self) -> str:
    valve = '_valve4' if self.valve4 else ''
    return f'{self.domain}_{self.task}{valve}_{self.algo}_seed{self.seed}'

  @property
  def task_kwargs(self) -> dict[str, Any]:
    kwargs = {'valve': 'valve4'} if self.valve4 else {}
    if self.algo == PLAN.get('constrained_agent'):
      # The constrained agent acts through the plan's action map.
      kwargs['action_map'] = PLAN['constrained_action_map']
    return kwargs

  @property
  def fixed(self) -> bool:
    return (self.domain, self.task) in suite.FIXED

  @property
  def directory(self) -> pathlib.Path:
    return RUNS_DIR / self.name

  def source(self) -> 'Run | None':
    """The run this one starts from (its agent's `starts_from`): the
    default agent's run, same seed, of the Random variant ('random') or of
    this task ('same'); else None."""
    from robel_dm.learning import agents  # noqa: PLC0415

    starts_from = agents.get(self.algo).starts_from
    if starts_from is None:
      return None
    task = self.task
    if starts_from == 'random':
      task = task.removesuffix('_dynamics')
    return Run(self.domain, task, PLAN['default_agent'], self.seed, self.valve4)

  def config(self, demos: tuple[str, ...] = ()):
    from robel_dm.learning import agents, training  # noqa: PLC0415

    settings = PLAN['tasks'][f'{self.domain}/{self.task}']
    steps, every = settings['steps'], settings['eval_every']
    # An agent may have a budget of its own: on every task (one that starts
    # from a trained policy), or on one task (where its curve still rose).
    steps = settings.get('agent_steps', {}).get(
      self.algo, PLAN.get('agent_steps', {}).get(self.algo, steps)
    )
    kind = agents.get(self.algo).kind
    if kind == agents.ON_POLICY:
      steps = min(steps * PLAN['on_policy_factor'], PLAN['on_policy_max_steps'])
      every *= PLAN['on_policy_factor']
    elif kind == agents.IMITATION:
      steps, every = PLAN['bc_epochs'], PLAN['bc_epochs'] // 10
    return training.RunConfig(
      domain=self.domain,
      task=self.task,
      task_kwargs=self.task_kwargs,
      algo=self.algo,
      seed=self.seed,
      steps=steps,
      eval_every=every,
      eval_episodes=1 if self.fixed else PLAN['eval_episodes_random'],
      demos=demos,
      demo_episodes=PLAN['demo_episodes'],
      # Behaviour cloning fits its epochs whatever they read.
      stop_at_success=(
        PLAN['solved']
        if PLAN['stop_when_solved'] and kind != agents.IMITATION
        else None
      ),
      # A Fixed task's evaluation is one deterministic episode; a Random
      # one's, a sample: it must hold the rate over more than one.
      stop_streak=1 if self.fixed else PLAN['stop_streak_random'],
      init_from=str(self.source().directory) if self.source() else None,
    )


def runs() -> list[Run]:
  """Every run of the table, in the order they are worth running: the
  default agent on the Fixed tasks (every seed), then on the Random ones,
  then on RandomDynamics and the 4-prong valve, then the other agents,
  then the constrained agent (under a safety budget), then the agents
  tried `also` on tasks the default agent left unsolved."""
  return (
    _default_agent_runs()
    + _every_agent_runs()
    + _constrained_runs()
    + _also_runs()
  )


def _run(key: str, algo: str, seed: int) -> Run:
  """The run of `algo` on the plan's task `key` ('domain/task')."""
  domain, task = key.split('/')
  return Run(domain, task, algo, seed)


def _tier(domain: str, task: str) -> str:
  """Which of the default agent's tiers a task is in."""
  if (domain, task) in suite.FIXED:
    return 'fixed'
  if (domain, task) in suite.RANDOM:
    return 'random'
  return 'other'


def _default_agent_runs() -> list[Run]:
  """The default agent on every task, tier by tier (Fixed, Random, the
  rest with the 4-prong valve), each tier seed by seed."""
  tiers = {'fixed': [], 'random': [], 'other': []}
  for key in PLAN['tasks']:
    domain, task = key.split('/')
    tiers[_tier(domain, task)].append((domain, task, False))
    if key in PLAN['valve4']:
      tiers['other'].append((domain, task, True))
  return [
    Run(domain, task, PLAN['default_agent'], seed, valve4)
    for tier in tiers.values()
    for seed in PLAN['seeds']
    for domain, task, valve4 in tier
  ]


def _every_agent_runs() -> list[Run]:
  """The other agents on the `every_agent` tasks, seed by seed."""
  return [
    _run(key, algo, seed)
    for seed in PLAN['seeds']
    for key in PLAN['every_agent']
    for algo in PLAN['agents']
    if algo != PLAN['default_agent']
  ]


def _constrained_runs() -> list[Run]:
  """The constrained agent on the `constrained` tasks, seed by seed."""
  return [
    _run(key, PLAN['constrained_agent'], seed)
    for seed in PLAN['seeds']
    for key in PLAN.get('constrained', [])
  ]


def _also_runs() -> list[Run]:
  """The agents tried `also` on a task, on every seed (those not already
  in `_every_agent_runs`)."""
  return [
    _run(key, algo, seed)
    for key, algos in PLAN.get('also', {}).items()
    for seed in PLAN['seeds']
    for algo in algos
    if key not in PLAN['every_agent'] or algo not in PLAN['agents']
  ]


def select(pattern: str | None) -> list[Run]:
  """The plan's runs whose names match `pattern`: fnmatch patterns,
  comma-separated (any of them), in plan order; all runs if None.

  Raises:
    ValueError: naming a pattern that matches no run.
  """
  table = runs()
  if not pattern:
    return table
  patterns = [part for part in pattern.split(',') if part]
  for part in patterns:
    if not any(fnmatch.fnmatch(r.name, part) for r in table):
      raise ValueError(f'no run of the table matches {part!r}')
  return [r for r in table if any(fnmatch.fnmatch(r.name, p) for p in patterns)]


def evaluations(run: Run) -> list[dict]:
  """The run's training evaluations so far (none before it starts)."""
  from robel_dm.learning import curves, training  # noqa: PLC0415

  path = run.directory / training.EVAL_LOG
  return curves.read_log(path) if path.is_file() else []


def finished(run: Run) -> bool:
  """Whether the run's test episodes were read (it is final)."""
  return (run.directory / TEST).is_file()


def variant(task_kwargs: dict[str, Any]) -> str:
  """Task arguments as a key (which valve, for the valve tasks)."""
  return json.dumps(task_kwargs, sort_keys=True)


def _key(row: dict) -> tuple:
  return (
    row['domain'],
    row['task'],
    variant(row['task_kwargs']),
    row['algo'],
    row['seed'],
  )


def recorded_row(run: Run) -> dict | None:
  if not RESULTS.is_file():
    return None
  mine = _key(dataclasses.asdict(run) | {'task_kwargs': run.task_kwargs})
  rows = json.loads(RESULTS.read_text())
  return next((row for row in rows if _key(row) == mine), None)


def recorded(run: Run) -> bool:
  """Whether docs/baselines.json holds the run (its folder may be gone:
  run folders are not committed, the records are)."""
  return recorded_row(run) is not None


def _trained(curve_end: int | float, run: Run) -> bool:
  """Whether a run trained to the plan's budget: `curve_end` is its last
  evaluation's env steps (epochs for bc)."""
  return curve_end >= run.config().steps


def settled(run: Run) -> bool:
  """Whether the table holds the run's result under the current protocol.
  A record of an earlier protocol is made again (from its folder, or from
  the start where the folder is gone: runs are deterministic)."""
  row = recorded_row(run)
  return row is not None and row.get('protocol', 1) >= PROTOCOL


def in_progress(run: Run) -> bool:
  """Whether the run's folder holds a run begun and not finished (for a
  recorded run: one being made again, `--force`)."""
  from robel_dm.learning import training  # noqa: PLC0415

  return (run.directory / training.CONFIG).is_file() and not finished(run)


def done(run: Run) -> bool:
  """Whether the run needs no more training: its test was read, or its
  record is of the current protocol."""
  return finished(run) or settled(run)


def status(run: Run) -> str:
  """What `robel-baselines list` says of the run: 'being made again' (a
  recorded run whose remake is begun and not finished), 'in progress',
  'done', or '' (not begun)."""
  if in_progress(run):
    return 'being made again' if recorded(run) else 'in progress'
  return 'done' if done(run) else ''


def _curve_end(run: Run, rows: list[dict] | None = None) -> int | float:
  """The last evaluation's env steps (epochs for bc), from the run's log
  or from its `rows` if already read."""
  last = (evaluations(run) if rows is None else rows)[-1]
  return last.get('epoch', last['env_steps'])


def _best_policy_steps(
  rows: list[dict], until: int | float, budget: float | None
) -> int:
  """The env steps at which the run's best policy (as `train` keeps it,
  under the run's safety `budget`) was evaluated, among the evaluations up
  to `until` steps."""
  from robel_dm.learning import training  # noqa: PLC0415

  best = training.best_of(
    [row for row in rows if row['env_steps'] <= until], budget
  )
  return best['env_steps']


def _confirmed(run: Run, log=print) -> bool:
  """Whether the best policy of a Random-task run that stopped early holds
  the solved rate on `confirm_episodes_random` fresh episodes (seeded apart
  from training, its evaluations, the validation and the test episodes, and
  from each earlier confirmation). Its 10-episode evaluations, always the
  same episodes, can read 0.8 twice by luck: under protocol 1, two such
  stops read 0.64 and 0.52 on the final 50 episodes. A policy is checked
  once: checking the same one again until a reading passes would only
  select a lucky reading, so a run whose best policy was checked trains on
  until it has a new one (or to its budget). A constrained agent's policy
  must also keep its safety budget on those episodes."""
  from robel_dm import evaluation, policies  # noqa: PLC0415
  from robel_dm.learning import agents, training  # noqa: PLC0415

  path = run.directory / CONFIRMATIONS
  checked = (
    [json.loads(line) for line in path.read_text().splitlines()]
    if path.is_file()
    else []
  )
  rows = evaluations(run)
  steps = _curve_end(run, rows)
  budget = agents.get(run.algo).safety_budget
  policy_steps = _best_policy_steps(rows, steps, budget)
  if any(
    _best_policy_steps(rows, check['env_steps'], budget) == policy_steps
    for check in checked
  ):
    log(
      f'{run.name}: stopped at {steps:,} steps; its best policy (evaluated '
      f'at {policy_steps:,}) was checked before: training on'
    )
    return False
  earlier = len(checked)
  episodes = PLAN['confirm_episodes_random']
  seed = CONFIRM_SEED_OFFSET + run.seed * 10_000 + earlier * episodes
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      run.domain,
      run.task,
      episodes,
      policy=policies.load(run.directory / training.BEST_POLICY),
      seed=seed,
      task_kwargs=run.task_kwargs,
    )
  )
  rate = results['success_rate']
  line = {
    'env_steps': steps,
    'success': rate,
    'seed': seed,
    'policy_steps': policy_steps,
    'violations': results['safety'],
  }
  with open(path, 'a') as file:
    file.write(json.dumps(line) + '\n')
  # A constrained agent's run is solved only within its safety budget.
  held = rate >= PLAN['solved'] and training.within_budget(
    {'safety': results['safety']}, budget
  )
  log(
    f'{run.name}: stopped at {steps:,} steps; {episodes} fresh episodes '
    f'give {rate:.2f}, {sum(results["safety"].values()):.1f} violations per '
    f'episode: {"confirmed" if held else "training on"}'
  )
  return held


def solved(row: dict) -> bool:
  """Whether a record counts as solved: final success of at least the
  plan's bar (0.8)."""
  return row['success'] >= PLAN['solved']


def solved_safely(row: dict) -> bool:
  """Whether a record counts as solved with ROBEL-safe episodes: solved,
  with at most the plan's safe violations per test episode (all kinds)."""
  violations = sum(row['violations'].values())
  return solved(row) and violations <= PLAN['safe_violations']


def shipped_metadata(domain: str, task: str) -> dict | None:
  """The metadata of the task's policy in policies/, if one is there."""
  path = POLICIES / f'{domain}_{task}.npz'
  if not path.is_file():
    return None
  with np.load(path) as arrays:
    return json.loads(str(arrays['metadata']))


def train_run(run: Run, log=print, demos: tuple[str, ...] = ()) -> dict | None:
  """Trains `run` (resuming) until its validation says stop, keeps its best
  policy, reads its validation and then, once, its test episodes; returns
  its record. None if the run it starts from is not finished yet.

  Args:
    run: the run.
    log: where progress lines go.
    demos: the recordings of its demonstrations, for an agent that learns
      from them (`scheduling.make_run` makes them).

  Raises:
    ValueError: for an agent that learns from demonstrations, given none.
  """
  from robel_dm import policies  # noqa: PLC0415
  from robel_dm.learning import agents, training  # noqa: PLC0415

  if finished(run):
    return record(run)
  if agents.get(run.algo).needs_demos and not demos:
    raise ValueError(f'{run.name}: its agent learns from demonstrations')
  source = run.source()
  if source is not None and not finished(source):
    log(f'{run.name}: waits for {source.name} to start from{_why(source)}')
    return None
  config = run.config(demos)
  resume = (run.directory / training.CONFIG).is_file()
  run.directory.mkdir(parents=True, exist_ok=True)
  if not (run.directory / COMMIT).is_file():  # The code the run began with.
    (run.directory / COMMIT).write_text(_commit())
  while True:
    training.train(config, run.directory, resume=resume, log=log)
    resume = True
    # bc's epochs take seconds and it cannot resume: its stop stands.
    if (
      run.fixed
      or agents.get(run.algo).kind == agents.IMITATION
      or _trained(_curve_end(run), run)
      or _confirmed(run, log)
    ):
      break
  best = policies.load(run.directory / training.BEST_POLICY)
  _read(run, best, VALIDATION)
  _read(run, best, TEST)  # Last: nothing is decided after it.
  return record(run)


def interval(successes: float, episodes: int) -> tuple[float, float]:
  """The 95% Wilson interval of a success rate read on `episodes`
  independent episodes."""
  z = 1.959963984540054
  n = max(episodes, 1)
  centre = (successes + z * z / (2 * n)) / (1 + z * z / n)
  half = (z / (1 + z * z / n)) * np.sqrt(
    successes * (1 - successes) / n + z * z / (4 * n * n)
  )
  return max(0.0, centre - half), min(1.0, centre + half)


def _read(run: Run, policy, which: str) -> None:
  """Evaluates `policy` on the run's validation or test episodes into
  VALIDATION or TEST. A Fixed task has one episode, the same whatever its
  seed (the simulation and the policy's mean action are deterministic):
  its reading is exact."""
  from robel_dm import evaluation  # noqa: PLC0415

  offset, episodes = {
    VALIDATION: (VALIDATION_SEED_OFFSET, PLAN['validation_episodes_random']),
    TEST: (TEST_SEED_OFFSET, PLAN['test_episodes_random']),
  }[which]
  episodes = 1 if run.fixed else episodes
  seed = offset + run.seed * 10_000
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      run.domain,
      run.task,
      episodes,
      policy=policy,
      seed=seed,
      task_kwargs=run.task_kwargs,
    )
  )
  success = results['success_rate']
  reading = {
    'episodes': episodes,
    'seed': seed,
    'deterministic': run.fixed,
    'success': success,
    'interval': [success, success]
    if run.fixed
    else list(interval(success, episodes)),
    'score': results['mean_score'],
    'return': results['mean_return'],
    'violations': results['safety'],
  }
  (run.directory / which).write_text(json.dumps(reading, indent=1))


def _first_solved_evaluation(log: list[dict]) -> dict | None:
  """The first training evaluation at or above the solved rate."""
  return next(
    (row for row in log if row['success_rate'] >= PLAN['solved']), None
  )


def _why(source: Run) -> str:
  """What a run waiting for `source` needs, where the queue will not make
  it: a recorded source whose folder (its networks) is not here."""
  if not recorded(source) or in_progress(source):
    return ''
  return (
    f' (recorded, but its folder with the networks is not here: '
    f'robel-baselines train --only={source.name} --force makes it again)'
  )


def record(run: Run) -> dict:
  """The run's line of docs/baselines.json."""
  log = evaluations(run)
  test = json.loads((run.directory / TEST).read_text())
  validation = json.loads((run.directory / VALIDATION).read_text())
  last, reached = log[-1], _first_solved_evaluation(log)
  config = json.loads((run.directory / 'config.json').read_text())
  confirmations = run.directory / CONFIRMATIONS
  source = run.source()
  started_from = {}
  if source is not None:
    # Its networks had learned from the source's env steps first.
    end = evaluations(source)[-1]
    started_from = {
      'started_from': {
        'run': source.name,
        'env_steps': _curve_end(source),
        'minutes': {
          'wall': end['wall_time'] / 60,
          'cpu': end.get('cpu_time', 0.0) / 60,
        },
      }
    }
  return {
    **started_from,
    'domain': run.domain,
    'task': run.task,
    'task_kwargs': run.task_kwargs,
    'algo': run.algo,
    'seed': run.seed,
    'protocol': PROTOCOL,
    'env_steps': last['env_steps'],
    'budget': config['steps'],
    'success': test['success'],
    'success_interval': test['interval'],
    'score': test['score'],
    'final_episodes': test['episodes'],
    'test_seed': test['seed'],
    'deterministic': test['deterministic'],
    'validation': {
      key: validation[key]
      for key in ('success', 'score', 'episodes', 'seed', 'violations')
    },
    'steps_to_80': None if reached is None else reached['env_steps'],
    'minutes_to_80': None
    if reached is None
    else {
      'wall': reached['wall_time'] / 60,
      'cpu': reached.get('cpu_time', 0.0) / 60,
    },
    'violations': test['violations'],
    'wall_minutes': last['wall_time'] / 60,
    'cpu_minutes': last['cpu_time'] / 60,
    'commit': (run.directory / COMMIT).read_text().strip()
    if (run.directory / COMMIT).is_file()
    else 'unknown',
    'curve': [
      [row.get('epoch', row['env_steps']), row['success_rate']] for row in log
    ],
    # Early stops checked on fresh validation episodes (Random tasks).
    'confirmations': [
      json.loads(line) for line in confirmations.read_text().splitlines()
    ]
    if confirmations.is_file()
    else [],
  }


def _commit() -> str:
  try:
    return subprocess.run(
      ['git', 'rev-parse', '--short', 'HEAD'],
      cwd=ROOT,
      capture_output=True,
      text=True,
      check=True,
    ).stdout.strip()
  except (OSError, subprocess.CalledProcessError):
    return 'unknown'


def merge_results(records: list[dict]) -> None:
  """Adds or replaces records in docs/baselines.json (by run identity);
  queues in other processes wait their turn."""
  RESULTS.parent.mkdir(parents=True, exist_ok=True)
  with open(RESULTS.with_suffix('.lock'), 'w') as lock:
    fcntl.flock(lock, fcntl.LOCK_EX)
    _merge(records)


def _merge(records: list[dict]) -> None:
  existing = json.loads(RESULTS.read_text()) if RESULTS.is_file() else []
  merged = {_key(row): row for row in existing}
  merged.update({_key(row): row for row in records})
  _write(list(merged.values()))


def _write(rows: list[dict]) -> None:
  rows = sorted(rows, key=_key)
  temporary = RESULTS.with_suffix('.partial')
  temporary.write_text(json.dumps(rows, indent=1) + '\n')
  temporary.replace(RESULTS)


def forget(run: Run) -> None:
  """Removes the run's folder, so that `train_run` makes it again; its
  record stays until the new one replaces it."""
  import shutil  # noqa: PLC0415

  shutil.rmtree(run.directory, ignore_errors=True)
