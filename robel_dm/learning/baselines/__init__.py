r"""The baseline table: its runs, how to run them, and its report.

    # Run the table (resumable; one process per core, or a Ray cluster):
    python -m robel_dm.learning.baselines train --queue=0 --queues=2 &
    python -m robel_dm.learning.baselines train --queue=1 --queues=2 &
    python -m robel_dm.learning.baselines train --ray_address=auto
    # One run, or a selection (fnmatch patterns on the run names):
    python -m robel_dm.learning.baselines train --only='dclaw_pose_*'
    # docs/baselines.json, docs/baselines.md's table and one figure per task:
    python -m robel_dm.learning.baselines report

The runs come from `plan.json` (tasks, budgets, seeds, agents). Each run
trains with `robel_dm.learning.train` into `runs/baselines/<name>/`, then
its best policy is evaluated afresh (`final.json`): once on a Fixed task
(whose episodes are all the same one, the simulation being deterministic),
on `final_episodes_random` episodes with unused seeds on the others.
Demonstrations (bc, sac_demos) come from `demonstrations`; a run whose
demonstrations cannot be made yet waits for a later pass.
"""

import dataclasses
import fcntl
import fnmatch
import json
import pathlib
import subprocess
import time
from typing import Any

import numpy as np

from robel_dm import suite

ROOT = pathlib.Path(__file__).resolve().parents[3]
PLAN = json.loads((pathlib.Path(__file__).with_name('plan.json')).read_text())
RUNS_DIR = ROOT / 'runs' / 'baselines'
RESULTS = ROOT / 'docs' / 'baselines.json'
DOC = ROOT / 'docs/baselines.md'
FIGURES = ROOT / 'docs' / 'baselines'
POLICIES = ROOT / 'policies'
FINAL = 'final.json'
COMMIT = 'commit.txt'
# Final evaluations are seeded apart from training and training evaluations.
FINAL_SEED_OFFSET = 2_000_000
CONFIRM_SEED_OFFSET = 6_000_000
CONFIRMATIONS = 'confirmations.jsonl'


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
    return {'valve': 'valve4'} if self.valve4 else {}

  @property
  def fixed(self) -> bool:
    return (self.domain, self.task) in suite.FIXED

  @property
  def directory(self) -> pathlib.Path:
    return RUNS_DIR / self.name

  def config(self, demos: tuple[str, ...] = ()):
    from robel_dm.learning import agents, train  # noqa: PLC0415

    settings = PLAN['tasks'][f'{self.domain}/{self.task}']
    steps, every = settings['steps'], settings['eval_every']
    kind = agents.get(self.algo).kind
    if kind == agents.ON_POLICY:
      steps = min(steps * PLAN['on_policy_factor'], PLAN['on_policy_max_steps'])
      every *= PLAN['on_policy_factor']
    elif kind == agents.IMITATION:
      steps, every = PLAN['bc_epochs'], PLAN['bc_epochs'] // 10
    return train.RunConfig(
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
      stop_at_success=PLAN['solved'] if PLAN['stop_when_solved'] else None,
      # A Fixed task's evaluation is one deterministic episode; a Random
      # one's, a sample: it must hold the rate over more than one.
      stop_streak=1 if self.fixed else PLAN['stop_streak_random'],
    )


def runs() -> list[Run]:
  """Every run of the table, in the order they are worth running: the
  default agent on the Fixed tasks (every seed), then on the Random ones,
  then on RandomDynamics and the 4-prong valve, then the other agents,
  then the agents tried `also` on tasks the default agent left unsolved."""
  tiers = {'fixed': [], 'random': [], 'other': []}
  for key in PLAN['tasks']:
    domain, task = key.split('/')
    if (domain, task) in suite.FIXED:
      tiers['fixed'].append((domain, task, False))
    elif (domain, task) in suite.RANDOM:
      tiers['random'].append((domain, task, False))
    else:
      tiers['other'].append((domain, task, False))
    if key in PLAN['valve4']:
      tiers['other'].append((domain, task, True))
  table = []
  for tier in tiers.values():
    for seed in PLAN['seeds']:
      for domain, task, valve4 in tier:
        table.append(Run(domain, task, PLAN['default_agent'], seed, valve4))
  for seed in PLAN['seeds']:
    for key in PLAN['every_agent']:
      domain, task = key.split('/')
      for algo in PLAN['agents']:
        if algo != PLAN['default_agent']:
          table.append(Run(domain, task, algo, seed))
  for key, algos in PLAN.get('also', {}).items():
    domain, task = key.split('/')
    for seed in PLAN['seeds']:
      for algo in algos:
        if key not in PLAN['every_agent'] or algo not in PLAN['agents']:
          table.append(Run(domain, task, algo, seed))
  return table


def select(pattern: str | None) -> list[Run]:
  table = runs()
  if not pattern:
    return table
  chosen = [r for r in table if fnmatch.fnmatch(r.name, pattern)]
  if not chosen:
    raise ValueError(f'no run of the table matches {pattern!r}')
  return chosen


def evaluations(run: Run) -> list[dict]:
  """The run's training evaluations so far (none before it starts)."""
  from robel_dm.learning import curves, train  # noqa: PLC0415

  path = run.directory / train.EVAL_LOG
  return curves.read_log(path) if path.is_file() else []


def finished(run: Run) -> bool:
  return (run.directory / FINAL).is_file()


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


def _recorded_row(run: Run) -> dict | None:
  if not RESULTS.is_file():
    return None
  mine = _key(dataclasses.asdict(run) | {'task_kwargs': run.task_kwargs})
  rows = json.loads(RESULTS.read_text())
  return next((row for row in rows if _key(row) == mine), None)


def recorded(run: Run) -> bool:
  """Whether docs/baselines.json holds the run (its folder may be gone:
  run folders are not committed, the records are)."""
  return _recorded_row(run) is not None


def _trained(curve_end: int | float, run: Run) -> bool:
  """Whether a run trained to the plan's budget: `curve_end` is its last
  evaluation's env steps (epochs for bc)."""
  return curve_end >= run.config().steps


def _short_of_plan(success: float, curve_end: int | float, run: Run) -> bool:
  """Whether a result needs more training: unsolved, and trained less than
  the plan now gives the run (the plan raised its budget, or it stopped
  early on a streak of evaluations its final evaluation did not bear out)."""
  return success < PLAN['solved'] and not _trained(curve_end, run)


def settled(run: Run) -> bool:
  """Whether the table holds the run's result under the plan as it is:
  recorded, and solved or trained to the plan's budget. A run left
  unsolved short of the plan's budget goes on (from its folder, or from
  the start where the folder is gone); a solved one would have stopped at
  the same point under a larger budget, so it stands."""
  row = _recorded_row(run)
  return row is not None and not _short_of_plan(
    row['success'], row['curve'][-1][0], run
  )


def done(run: Run) -> bool:
  """Whether the run needs no more training under the plan."""
  if finished(run):
    final = json.loads((run.directory / FINAL).read_text())
    return not _short_of_plan(final['success'], _curve_end(run), run)
  return settled(run)


def _curve_end(run: Run, rows: list[dict] | None = None) -> int | float:
  """The last evaluation's env steps (epochs for bc), from the run's log
  or from its `rows` if already read."""
  last = (evaluations(run) if rows is None else rows)[-1]
  return last.get('epoch', last['env_steps'])


def _best_policy_steps(rows: list[dict], until: int | float) -> int:
  """The env steps at which the run's best policy (as `train` keeps it)
  was evaluated, among the evaluations up to `until` steps."""
  from robel_dm.learning import train  # noqa: PLC0415

  best = train.best_of([row for row in rows if row['env_steps'] <= until])
  return best['env_steps']


def _confirmed(run: Run, log=print) -> bool:
  """Whether the best policy of a Random-task run that stopped early holds
  the solved rate on `final_episodes_random` fresh episodes (seeded apart
  from training, its evaluations and the final evaluation, and apart from
  each earlier confirmation). Its 10-episode evaluations, always the same
  episodes, can read 0.8 twice by luck: two such stops gave 0.64 and 0.52
  on the final 50 episodes. A policy is checked once: checking the same
  one again until a reading passes would only select a lucky reading, so
  a run whose best policy was checked trains on until it has a new one
  (or to its budget)."""
  from robel_dm import evaluate, policies  # noqa: PLC0415
  from robel_dm.learning import train  # noqa: PLC0415

  path = run.directory / CONFIRMATIONS
  checked = (
    [json.loads(line) for line in path.read_text().splitlines()]
    if path.is_file()
    else []
  )
  rows = evaluations(run)
  steps = _curve_end(run, rows)
  policy_steps = _best_policy_steps(rows, steps)
  if any(
    _best_policy_steps(rows, check['env_steps']) == policy_steps
    for check in checked
  ):
    log(
      f'{run.name}: stopped at {steps:,} steps; its best policy (evaluated '
      f'at {policy_steps:,}) was checked before: training on'
    )
    return False
  earlier = len(checked)
  episodes = PLAN['final_episodes_random']
  seed = CONFIRM_SEED_OFFSET + run.seed * 10_000 + earlier * episodes
  results = evaluate.evaluate(
    run.domain,
    run.task,
    episodes,
    policy=policies.load(run.directory / train.BEST_POLICY),
    seed=seed,
    task_kwargs=run.task_kwargs,
  )
  rate = results['success_rate']
  line = {
    'env_steps': steps,
    'success': rate,
    'seed': seed,
    'policy_steps': policy_steps,
  }
  with open(path, 'a') as file:
    file.write(json.dumps(line) + '\n')
  held = rate >= PLAN['solved']
  log(
    f'{run.name}: stopped at {steps:,} steps; {episodes} fresh episodes '
    f'give {rate:.2f}: {"confirmed" if held else "training on"}'
  )
  return held


def solved(row: dict) -> bool:
  """Whether a record counts as solved: final success of at least the
  plan's bar (0.8)."""
  return row['success'] >= PLAN['solved']


def shipped_metadata(domain: str, task: str) -> dict | None:
  """The metadata of the task's policy in policies/, if one is there."""
  path = POLICIES / f'{domain}_{task}.npz'
  if not path.is_file():
    return None
  with np.load(path) as arrays:
    return json.loads(str(arrays['metadata']))


def best_policy(
  domain: str, task: str, rows: list[dict] | None = None
) -> pathlib.Path | None:
  """The policy of the task's best solved row (valve3; highest final
  success, then mean score) that is at hand: its run's best policy, or the
  shipped one if it is that row's. Run folders are not committed, so in a
  fresh clone the shipped policy stands until a better row's run is made.
  Without records, the shipped policy. `rows`: the records, if already
  read."""
  if rows is None:
    rows = json.loads(RESULTS.read_text()) if RESULTS.is_file() else []
  best_first = sorted(
    (
      row
      for row in rows
      if (row['domain'], row['task']) == (domain, task)
      and not row['task_kwargs']
      and solved(row)
    ),
    key=lambda row: (row['success'], row['score']),
    reverse=True,
  )
  shipped = POLICIES / f'{domain}_{task}.npz'
  metadata = shipped_metadata(domain, task)
  for row in best_first:
    source = Run(domain, task, row['algo'], row['seed']).directory
    if (source / 'policy_best.npz').is_file():
      return source / 'policy_best.npz'
    if metadata and (metadata['algo'], metadata['seed']) == (
      row['algo'],
      row['seed'],
    ):
      return shipped
  return shipped if metadata and not best_first else None


def train_run(run: Run, log=print) -> dict | None:
  """Trains `run` (resuming), evaluates its best policy, returns its
  record; None if its demonstrations cannot be made yet."""
  from robel_dm import evaluate, policies  # noqa: PLC0415
  from robel_dm.learning import agents, train  # noqa: PLC0415

  if finished(run):
    if done(run):
      return record(run)
    # The plan raised an unsolved run's budget: it trains on from here.
    (run.directory / FINAL).unlink()
  demos = ()
  if agents.get(run.algo).needs_demos:
    from robel_dm.learning.baselines import demonstrations  # noqa: PLC0415

    source = demonstrations.record(run, log)
    if source is None:
      log(f'{run.name}: waits for a solved policy to demonstrate the task')
      return None
    demos = (source,)
  config = run.config(demos)
  resume = (run.directory / train.CONFIG).is_file()
  run.directory.mkdir(parents=True, exist_ok=True)
  if not (run.directory / COMMIT).is_file():  # The code the run began with.
    (run.directory / COMMIT).write_text(_commit())
  while True:
    train.train(config, run.directory, resume=resume, log=log)
    resume = True
    # bc's epochs take seconds and it cannot resume: its stop stands.
    if (
      run.fixed
      or agents.get(run.algo).kind == agents.IMITATION
      or _trained(_curve_end(run), run)
      or _confirmed(run, log)
    ):
      break
  best = policies.load(run.directory / train.BEST_POLICY)
  episodes = 1 if run.fixed else PLAN['final_episodes_random']
  results = evaluate.evaluate(
    run.domain,
    run.task,
    episodes,
    policy=best,
    seed=FINAL_SEED_OFFSET + run.seed * 1000,
    task_kwargs=run.task_kwargs,
  )
  final = {
    'episodes': episodes,
    'deterministic': run.fixed,
    'success': results['success_rate'],
    'score': results['mean_score'],
    'return': results['mean_return'],
    'violations': results['safety'],
  }
  (run.directory / FINAL).write_text(json.dumps(final, indent=1))
  return record(run)


def record(run: Run) -> dict:
  """The run's line of docs/baselines.json."""
  log = evaluations(run)
  final = json.loads((run.directory / FINAL).read_text())
  last = log[-1]
  solved_at = next(
    (row['env_steps'] for row in log if row['success_rate'] >= PLAN['solved']),
    None,
  )
  config = json.loads((run.directory / 'config.json').read_text())
  confirmations = run.directory / CONFIRMATIONS
  return {
    'domain': run.domain,
    'task': run.task,
    'task_kwargs': run.task_kwargs,
    'algo': run.algo,
    'seed': run.seed,
    'env_steps': last['env_steps'],
    'budget': config['steps'],
    'success': final['success'],
    'score': final['score'],
    'final_episodes': final['episodes'],
    'deterministic': final['deterministic'],
    'steps_to_80': solved_at,
    'violations': final['violations'],
    'wall_minutes': last['wall_time'] / 60,
    'cpu_minutes': last['cpu_time'] / 60,
    'commit': (run.directory / COMMIT).read_text().strip()
    if (run.directory / COMMIT).is_file()
    else 'unknown',
    'curve': [
      [row.get('epoch', row['env_steps']), row['success_rate']] for row in log
    ],
    # Early stops checked on fresh episodes (Random tasks), in order.
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
  rows = sorted(merged.values(), key=_key)
  temporary = RESULTS.with_suffix('.partial')
  temporary.write_text(json.dumps(rows, indent=1) + '\n')
  temporary.replace(RESULTS)


def train_queue(
  queue: int, queues: int, pattern: str | None, hours: float | None
) -> None:
  """Runs this queue's share of the table, round robin, resuming; runs
  that wait for demonstrations are tried again after the others."""
  deadline = time.monotonic() + hours * 3600 if hours else None
  mine = [r for i, r in enumerate(select(pattern)) if i % queues == queue]
  waiting = []
  for run in mine:
    if deadline and time.monotonic() > deadline:
      print('time budget used up; the rest resumes on the next call')
      return
    if done(run) and not finished(run):
      continue
    result = train_run(run, log=lambda line: print(line, flush=True))
    if result is None:
      waiting.append(run)
    else:
      merge_results([result])
  for run in waiting:
    result = train_run(run, log=lambda line: print(line, flush=True))
    if result is not None:
      merge_results([result])


def _remote_train_run(run: Run, plan: dict, runs_dir: pathlib.Path):
  """`train_run` in a Ray worker, with the driver's plan and run folder."""
  global PLAN, RUNS_DIR  # noqa: PLW0603 (a worker process of its own)
  PLAN, RUNS_DIR = plan, runs_dir
  return train_run(run, log=lambda line: None)


def train_ray(address: str, pattern: str | None) -> list[dict]:
  """Every selected run as a Ray task (one CPU each); the records merged
  into docs/baselines.json as they end. `address` 'local' starts a Ray
  instance on this machine for the call."""
  from robel_dm import parallel  # noqa: PLC0415

  chosen = [run for run in select(pattern) if finished(run) or not done(run)]
  with parallel.ray_session(address) as ray:
    remote = ray.remote(num_cpus=1)(_remote_train_run)
    pending = {remote.remote(run, PLAN, RUNS_DIR): run for run in chosen}
    records = []
    while pending:
      ready, _ = ray.wait(list(pending))
      for ref in ready:
        run = pending.pop(ref)
        result = ray.get(ref)
        if result is not None:
          records.append(result)
          merge_results([result])
        print(f'{run.name}: {"done" if result else "waits for demos"}')
    return records
