"""The baseline table: its plan, runs, records, report and Ray fan-out."""

import contextlib
import copy
import itertools
import json
import shutil
import types

import numpy as np
import pytest

pytest.importorskip('sbx', reason='needs robel_dm[learn]')

from robel_dm import suite  # noqa: E402
from robel_dm.commands import baselines as cli  # noqa: E402
from robel_dm.evaluation import task_args, workers  # noqa: E402
from robel_dm.learning import agents, baselines, training  # noqa: E402
from robel_dm.learning.baselines import (  # noqa: E402
  demonstrations,
  report,
  scheduling,
  selection,
)

FIELDS = {'domain', 'task', 'task_kwargs', 'algo', 'seed', 'env_steps',
          'success', 'score', 'steps_to_80', 'violations', 'wall_minutes',
          'cpu_minutes', 'commit'}  # fmt: skip


def test_the_plan_covers_every_task_seed_and_kind_of_agent():
  table = baselines.runs()
  default = [r for r in table if r.algo == agents.DEFAULT and not r.valve4]
  assert {(r.domain, r.task) for r in default} == set(suite.ALL_TASKS)
  for domain, task in suite.ALL_TASKS:
    seeds = {r.seed for r in default if (r.domain, r.task) == (domain, task)}
    assert len(seeds) >= 3, (domain, task)
  valve4 = {(r.task, r.seed) for r in table if r.valve4}
  assert {task for task, _ in valve4} == {
    'turn_fixed', 'turn_random', 'screw_fixed', 'screw_random'
  }  # fmt: skip
  kinds = {}
  for run in table:
    kinds.setdefault((run.task, run.seed), set()).add(
      agents.get(run.algo).paper
    )
  for family in ('turn', 'walk', 'pose', 'stand'):
    for variant in ('fixed', 'random'):
      for seed in (0, 1, 2):
        assert kinds[(f'{family}_{variant}', seed)] == {
          'SAC', 'NPG', 'BC', 'DAPG'
        }  # fmt: skip
  names = [run.name for run in table]
  assert len(names) == len(set(names))
  # Agents tried also where the default agent left a seed unsolved, on
  # every seed, after the rest.
  plan = copy.deepcopy(baselines.PLAN)
  with pytest.MonkeyPatch.context() as patch:
    patch.setattr(baselines, 'PLAN', plan)
    plan['also'] = {}
    without = baselines.runs()
    plan['also'] = {'dclaw/screw_fixed': ['sac_demos']}
    also = baselines.runs()[len(without) :]
  assert [(r.task, r.algo, r.seed) for r in also] == [
    ('screw_fixed', 'sac_demos', seed) for seed in (0, 1, 2)
  ]
  # Fixed tasks on every seed come first, then the Random ones.
  first = {(r.domain, r.task) for r in table[: 3 * len(suite.FIXED)]}
  assert first == set(suite.FIXED)


def test_the_table_stops_a_run_once_it_is_solved():
  config = baselines.Run('dclaw', 'turn_fixed', 'sac', 1).config()
  assert config.stop_at_success == baselines.PLAN['solved']
  assert config.stop_streak == 1  # One deterministic episode is the task.
  random = baselines.Run('dclaw', 'turn_random', 'sac', 1).config()
  assert random.stop_streak == 2  # A sample of 10 episodes: twice.


@pytest.mark.parametrize(
  'rates, streak, stops',
  [
    ([0.0, 0.9], 1, True),
    ([0.0, 0.9], 2, False),
    ([0.9, 0.7, 0.9], 2, False),
    ([0.7, 0.8, 0.9], 2, True),
  ],
)
def test_a_run_stops_after_a_streak_of_solved_evaluations(
  tmp_path, rates, streak, stops
):
  from robel_dm.learning import training  # noqa: PLC0415

  config = training.RunConfig(
    'dclaw', 'pose_random', stop_at_success=0.8, stop_streak=streak
  )
  run = training.Run(tmp_path, config, log=lambda line: None)
  run.history = [{'success_rate': rate} for rate in rates]
  assert run.solved(run.history[-1]) == stops


def _evaluation(success: float, violations: float, score: float = 0.0):
  return {
    'success_rate': success,
    'mean_score': score,
    'safety': {'position': violations, 'velocity': 0.0, 'current': 0.0},
  }


@pytest.mark.parametrize('algo, stops', [('sac', True), ('sac_safe', False)])
def test_a_constrained_run_stops_only_within_its_budget(tmp_path, algo, stops):
  from robel_dm.learning import training  # noqa: PLC0415

  config = training.RunConfig(
    'dclaw', 'pose_random', algo=algo, stop_at_success=0.8, stop_streak=2
  )
  run = training.Run(tmp_path, config, log=lambda line: None)
  # Solved twice, the second time over sac_safe's budget of 10.
  run.history = [_evaluation(0.9, 3.0), _evaluation(0.9, 25.0)]
  assert run.solved(run.history[-1]) == stops
  # Two in a row within it (10 is within a budget of 10).
  run.history += [_evaluation(1.0, 10.0), _evaluation(0.8, 0.0)]
  assert run.solved(run.history[-1])


def test_a_constrained_run_keeps_its_best_policy_within_budget():
  from robel_dm.learning import training  # noqa: PLC0415

  rows = [
    _evaluation(0.7, 4.0),
    _evaluation(1.0, 30.0),
    _evaluation(0.7, 9.0, 1),
  ]
  assert training.best_of(rows) is rows[1]
  assert training.best_of(rows, budget=10.0) is rows[2]
  # None within it: the best success, as without a budget.
  assert training.best_of(rows[1:2] + rows[1:2], budget=1.0) is rows[1]


@pytest.mark.slow
def test_a_constrained_runs_confirmation_must_keep_its_budget(
  sandbox, monkeypatch
):
  from robel_dm import evaluation  # noqa: PLC0415
  from robel_dm.learning import training  # noqa: PLC0415

  real_policy, real_evaluate = training.evaluate_policy, evaluation.evaluate
  unsafe = {'position': 50.0, 'velocity': 0.0, 'current': 0.0}
  safe = {'position': 0.0, 'velocity': 0.0, 'current': 0.0}

  def solved_safely(*args, **kwargs):  # Training evaluations: within budget.
    return real_policy(*args, **kwargs) | {'success_rate': 1.0, 'safety': safe}

  def solved_unsafely(*args, **kwargs):  # Fresh episodes: over it.
    return real_evaluate(*args, **kwargs) | {'success_rate': 1.0,
                                             'safety': unsafe}  # fmt: skip

  monkeypatch.setattr(training, 'evaluate_policy', solved_safely)
  monkeypatch.setattr(evaluation, 'evaluate', solved_unsafely)
  baselines.PLAN['tasks']['dclaw/pose_random'] = {'steps': 32, 'eval_every': 8}
  lines = []
  run = baselines.Run('dclaw', 'pose_random', 'sac_safe', 0)
  record = baselines.train_run(run, log=lines.append)
  confirmations = record['confirmations']
  assert confirmations and all(c['violations'] == unsafe for c in confirmations)
  assert record['env_steps'] == 32  # Trained on to its budget.
  assert any('50.0 violations per episode: training on' in x for x in lines)


@pytest.fixture
def sandbox(tmp_path, monkeypatch):
  """The table's paths and a tiny plan (pose and stand only)."""
  plan = copy.deepcopy(baselines.PLAN)
  plan.update(seeds=[0], confirm_episodes_random=3, eval_episodes_random=2,
              validation_episodes_random=3, test_episodes_random=4,
              demo_episodes=2, bc_epochs=20)  # fmt: skip
  plan['tasks'] = {
    'dclaw/pose_fixed': {'steps': 16, 'eval_every': 16},
    'dclaw/pose_random': {'steps': 16, 'eval_every': 8},
  }
  plan['valve4'], plan['every_agent'] = [], ['dclaw/pose_random']
  plan['also'], plan['constrained'] = {}, []
  monkeypatch.setattr(baselines, 'PLAN', plan)
  for name, path in (('RUNS_DIR', 'runs'), ('RESULTS', 'docs/b.json'),
                     ('DOC', 'docs/table.txt'), ('FIGURES', 'docs/figures'),
                     ('README', 'README.md'),
                     ('POLICIES', 'policies')):  # fmt: skip
    monkeypatch.setattr(baselines, name, tmp_path / path)
  monkeypatch.setattr(demonstrations, 'DIRECTORY', tmp_path / 'demonstrators')
  (tmp_path / 'policies').mkdir()
  return tmp_path


@pytest.mark.slow
def test_a_run_ends_with_validation_then_one_test_reading(sandbox, monkeypatch):
  from robel_dm import evaluation  # noqa: PLC0415

  real, seeds = evaluation.evaluate, []

  def spy(config, **reuse):
    seeds.append(config.seed)
    return real(config, **reuse)

  monkeypatch.setattr(evaluation, 'evaluate', spy)
  run = baselines.Run('dclaw', 'pose_random', 'sac', 0)
  record = baselines.train_run(run, log=lambda line: None)
  assert set(record) >= FIELDS
  assert record['protocol'] == baselines.PROTOCOL == 2
  assert record['env_steps'] == 16 and record['final_episodes'] == 4
  assert not record['deterministic']
  low, high = record['success_interval']
  assert 0 <= low <= record['success'] <= high <= 1 and high - low > 0.3
  assert record['validation']['episodes'] == 3
  # Validation, then the test, last, on seeds of its own.
  test_seed = baselines.TEST_SEED_OFFSET
  assert seeds[-2:] == [baselines.VALIDATION_SEED_OFFSET, test_seed]
  assert record['test_seed'] == test_seed and seeds.count(test_seed) == 1
  # A finished run is neither trained nor read again.
  assert baselines.train_run(run, log=print) == record
  assert seeds.count(test_seed) == 1
  fixed = baselines.train_run(
    baselines.Run('dclaw', 'pose_fixed', 'sac', 0), log=lambda line: None
  )
  assert fixed['deterministic'] and fixed['final_episodes'] == 1
  assert fixed['success_interval'] == [fixed['success']] * 2


def test_wilson_interval():
  assert baselines.interval(0.8, 50) == pytest.approx((0.670, 0.888), abs=1e-3)
  assert baselines.interval(1.0, 100)[1] == 1.0


def _lucky_run(monkeypatch, rising: bool):
  """Trains Pose Random's seed-0 run (32 steps, evaluated every 8) where
  every training evaluation reads success 1.0 (a lucky streak); with
  `rising`, each one's mean score beats the last, so each is the new best
  policy, else the first stays the best. Returns (run, record, log lines)."""
  from robel_dm.learning import training  # noqa: PLC0415

  real, count = training.evaluate_policy, itertools.count()

  def lucky(*args, **kwargs):
    score = float(next(count)) if rising else 0.5
    return real(*args, **kwargs) | {'success_rate': 1.0, 'mean_score': score}

  monkeypatch.setattr(training, 'evaluate_policy', lucky)
  baselines.PLAN['tasks']['dclaw/pose_random'] = {'steps': 32, 'eval_every': 8}
  run = baselines.Run('dclaw', 'pose_random', 'sac', 0)
  lines = []
  return run, baselines.train_run(run, log=lines.append), lines


@pytest.mark.slow
def test_an_early_stop_must_hold_on_fresh_episodes(sandbox, monkeypatch):
  # The lucky streak stops the run at its second evaluation; fresh episodes
  # of the (untrained) best policy fail, so it trains on, stopping and
  # checking each new best policy, to its budget.
  run, record, lines = _lucky_run(monkeypatch, rising=True)
  assert record['env_steps'] == 32 and record['success'] < 0.8
  assert [c['env_steps'] for c in record['confirmations']] == [8, 16, 24]
  assert sum('training on' in line for line in lines) == 3
  # Each check has episodes of its own, apart from validation and test.
  seeds = [c['seed'] for c in record['confirmations']]
  assert len(set(seeds)) == 3
  assert not {record['test_seed'], record['validation']['seed']} & set(seeds)
  assert baselines.done(run)
  # A record of the first protocol (no test episodes of its own) is made
  # again, from the start where its folder is gone.
  old = {k: v for k, v in record.items() if k != 'protocol'}
  baselines.merge_results([old])
  shutil.rmtree(baselines.RUNS_DIR)
  assert not baselines.settled(run) and not baselines.done(run)


@pytest.mark.slow
def test_a_best_policy_is_checked_once(sandbox, monkeypatch):
  # The best policy stays the first evaluated one: after its check fails,
  # later stops do not test it again (that would only wait for a lucky
  # reading); the run trains to its budget.
  _, record, lines = _lucky_run(monkeypatch, rising=False)
  assert record['env_steps'] == 32
  assert record['confirmations'] == [
    {
      'env_steps': 8,
      'success': record['confirmations'][0]['success'],
      'seed': baselines.CONFIRM_SEED_OFFSET,
      'policy_steps': 0,
      'violations': record['confirmations'][0]['violations'],
    }
  ]
  assert sum('was checked before: training on' in line for line in lines) == 2


@pytest.mark.slow
def test_demonstration_runs_use_the_reference_controller(sandbox):
  pytest.importorskip('pyarrow', reason='needs robel_dm[data]')  # Demos.
  run = baselines.Run('dclaw', 'pose_random', 'bc', 0)
  record = scheduling.make_run(run, log=lambda line: None)
  assert record['algo'] == 'bc' and record['env_steps'] == 0
  demos = sandbox / 'runs' / 'demos' / 'dclaw_pose_random'
  assert len((demos / 'meta' / 'episodes.jsonl').read_text().splitlines()) == 2


@pytest.mark.slow
def test_runs_without_a_demonstrator_wait(sandbox, monkeypatch):
  monkeypatch.setitem(
    baselines.PLAN['tasks'], 'dclaw/turn_fixed', {'steps': 8, 'eval_every': 8}
  )
  run = baselines.Run('dclaw', 'turn_fixed', 'bc', 0)
  lines = []
  assert scheduling.make_run(run, log=lines.append) is None
  assert 'waits for a solved policy' in lines[0]
  with pytest.raises(ValueError, match='learns from demonstrations'):
    baselines.train_run(run, log=lines.append)


@pytest.mark.slow
def test_a_shipped_policy_demonstrates_in_a_checkout_without_runs(
  sandbox, monkeypatch
):
  pytest.importorskip('pyarrow', reason='needs robel_dm[data]')  # Demos.
  # A fresh clone has policies/ but not runs/: demonstrations must not wait.
  monkeypatch.setitem(
    baselines.PLAN['tasks'], 'dclaw/turn_fixed', {'steps': 8, 'eval_every': 8}
  )
  shipped = baselines.ROOT / 'policies' / 'dclaw_turn_fixed.npz'
  shutil.copy(shipped, sandbox / 'policies' / 'dclaw_turn_fixed.npz')
  assert selection.best_policy('dclaw', 'turn_fixed') == (
    sandbox / 'policies' / 'dclaw_turn_fixed.npz'
  )
  run = baselines.Run('dclaw', 'turn_fixed', 'bc', 0)
  lines = []
  assert scheduling.make_run(run, log=lines.append) is not None
  assert 'demonstrations of dclaw/turn_fixed by' in lines[0]


@pytest.mark.slow
def test_a_pinned_demonstrator_demonstrates_until_it_changes(
  sandbox, monkeypatch
):
  pytest.importorskip('pyarrow', reason='needs robel_dm[data]')  # Demos.
  # The table's best policy of the task differs from its demonstrator; the
  # demonstrator records, once, and again when it is replaced.
  monkeypatch.setitem(
    baselines.PLAN['tasks'], 'dclaw/turn_fixed', {'steps': 8, 'eval_every': 8}
  )
  pinned = demonstrations.demonstrator('dclaw', 'turn_fixed')
  pinned.parent.mkdir()
  committed = baselines.ROOT / 'docs' / 'baselines' / 'demonstrators'
  shipped = baselines.ROOT / 'policies' / 'dclaw_turn_fixed.npz'
  shutil.copy(committed / 'dclaw_turn_fixed.npz', pinned)
  shutil.copy(shipped, sandbox / 'policies')
  run = baselines.Run('dclaw', 'turn_fixed', 'bc', 0)
  lines = []
  directory = demonstrations.record(run, lines.append)
  assert lines == [f'demonstrations of dclaw/turn_fixed by {pinned}']
  assert demonstrations.record(run, lines.append) == directory
  assert len(lines) == 1  # Kept, not made again.
  shutil.copy(shipped, pinned)
  demonstrations.record(run, lines.append)
  assert lines[1:] == [f'demonstrations of dclaw/turn_fixed by {pinned}']


@pytest.mark.slow
@pytest.mark.parametrize('key', baselines.PLAN['every_agent'])
def test_a_task_without_a_controller_has_a_pinned_solved_demonstrator(key):
  # Every checkout must record the same demonstrations, whatever policy the
  # table ships at the time.
  domain, task = key.split('/')
  if task_args.unavailable('reference', domain, task, {}) is None:
    # Its controller demonstrates: a pinned policy would lie unused.
    assert not demonstrations.demonstrator(domain, task).exists()
    return
  with np.load(demonstrations.demonstrator(domain, task)) as arrays:
    metadata = json.loads(str(arrays['metadata']))
  assert (metadata['domain'], metadata['task']) == (domain, task)
  assert not metadata['task_kwargs']
  rows = [
    row
    for row in json.loads(baselines.RESULTS.read_text())
    if (row['domain'], row['task'], row['algo'], row['seed'])
    == (domain, task, metadata['algo'], metadata['seed'])
    and not row['task_kwargs']
  ]
  assert len(rows) == 1 and baselines.solved(rows[0]), rows


def _row(algo, seed, validation, test, steps=1000, cpu=1.0) -> dict:
  """A Pose Random record: `validation` and `test` success."""
  return {
    'domain': 'dclaw', 'task': 'pose_random', 'task_kwargs': {},
    'algo': algo, 'seed': seed, 'protocol': 2, 'success': test,
    'score': 0.0, 'validation': {'success': validation, 'score': 0.0},
    'steps_to_80': steps, 'cpu_minutes': cpu,
  }  # fmt: skip


def test_the_agent_and_run_are_chosen_on_validation_not_test():
  baselines.PLAN['seeds']  # The real plan: 3 seeds.
  by_agent = {
    # Best test readings, but a seed short on validation.
    'trpo': [_row('trpo', s, v, 1.0) for s, v in enumerate((0.9, 0.9, 0.7))],
    'sac': [_row('sac', s, v, 0.8) for s, v in enumerate((0.9, 0.95, 0.85))],
    # As good on validation, but slower to 80%.
    'bc': [_row('bc', s, v, 0.8, steps=9000)
           for s, v in enumerate((0.9, 0.95, 0.85))],
  }  # fmt: skip
  choice = selection.choose(by_agent)
  assert choice.algo == 'sac' and choice.shipped['seed'] == 1
  assert 'solves 3 of 3 seeds on validation' in choice.why
  # An unsolved seed counts as more than the budget in the median.
  group = [_row('sac', s, 0.9, t) for s, t in enumerate((0.9, 0.5, 0.5))]
  assert selection.median_steps_to_80(group) == selection.UNSOLVED
  # Nothing solved on validation: nothing shipped.
  low = {'sac': [_row('sac', s, 0.5, 0.9) for s in range(3)]}
  assert selection.choose(low).shipped is None


def test_the_reason_names_the_readings_it_counts():
  group = [_row('sac', s, 0.9, 0.9) for s in range(3)]
  assert 'on validation (no other' in selection.choose({'sac': group}).why
  del group[0]['validation']  # A protocol-1 seed among protocol-2 ones.
  assert selection.choose({'sac': group}).why.startswith(
    'solves 3 of 3 seeds on validation (a seed recorded under protocol 1 '
    'has no validation reading: its reported success stands in)'
  )
  for row in group:
    row.pop('validation', None)
  assert 'on its reported success (protocol 1)' in (
    selection.choose({'sac': group}).why
  )


def test_an_agent_reading_privileged_state_is_never_recommended():
  by_agent = {
    'sac': [_row('sac', s, v, 0.8) for s, v in enumerate((0.9, 0.5, 0.5))],
    'sac_privileged': [_row('sac_privileged', s, 1.0, 1.0) for s in range(3)],
  }
  choice = selection.choose(by_agent)
  assert choice.algo == 'sac' and choice.shipped['seed'] == 0
  assert choice.why == (
    'solves 1 of 3 seeds on validation (the other agents recorded read what '
    'only a simulation knows)'
  )


def _safety(row, validation_violations, test_violations=0.0):
  """`row` with its validation and test violations per episode."""
  row['validation']['violations'] = {
    'position': validation_violations, 'velocity': 0.0, 'current': 0.0
  }  # fmt: skip
  row['violations'] = {'position': test_violations, 'velocity': 0.0,
                       'current': 0.0}  # fmt: skip
  return row


def test_safe_solved_runs_are_preferred_on_validation_violations():
  bar = baselines.PLAN['safe_violations']
  by_agent = {
    # Solves every seed, none within the budget (test readings safe).
    'sac': [_safety(_row('sac', s, 0.95, 0.95), 5 * bar) for s in range(3)],
    # Solves every seed too, two within it.
    'sac_safe': [
      _safety(_row('sac_safe', s, v, 0.9), vio, 5 * bar)
      for s, v, vio in ((0, 0.85, bar), (1, 0.9, 2 * bar), (2, 0.82, 0))
    ],
    # Solves two seeds, both safely: seeds solved come first.
    'trpo': [
      _safety(_row('trpo', s, v, 0.9), 0)
      for s, v in ((0, 0.9), (1, 0.9), (2, 0.5))
    ],
  }  # fmt: skip
  choice = selection.choose(by_agent)
  assert choice.algo == 'sac_safe'
  # A safe seed, though another has the higher validation success.
  assert choice.shipped['seed'] == 0
  assert choice.why == (
    'solves 3 of 3 seeds on validation, 2 of them within 10 violations per '
    'episode; next best `sac` 3 of 3, 0 within the limit'
  )
  # A Fixed task's validation episode is its test episode.
  fixed = _row('sac', 0, 1.0, 1.0)
  fixed['deterministic'] = True
  fixed['violations'] = {'position': 3.0, 'velocity': 0.0, 'current': 0.0}
  assert selection.safely_solved(fixed)
  # No violations read on validation (and not Fixed): not known safe.
  assert not selection.safely_solved(_row('sac', 0, 1.0, 1.0))
  # The tables count a record's test episodes: solved, and safely so.
  assert baselines.solved_safely(_safety(_row('sac', 0, 1.0, 0.9), 0, bar))
  unsafe = _safety(_row('sac', 0, 1.0, 0.9), 0, bar + 1)
  assert baselines.solved(unsafe) and not baselines.solved_safely(unsafe)


def test_a_seed_solved_safely_ships_where_the_recommended_agent_has_none():
  bar = baselines.PLAN['safe_violations']
  by_agent = {
    # Solves every seed, none within the budget: recommended.
    'sac': [_safety(_row('sac', s, 0.95, 0.95), 5 * bar) for s in range(3)],
    # Solves one seed, safely: its policy is the one for robots.
    'sac_safe': [
      _safety(_row('sac_safe', s, v, 0.9), 0)
      for s, v in ((0, 0.7), (1, 0.85), (2, 0.6))
    ],
    # A safe seed too, but the agent's policies need a simulation.
    'sac_privileged': [
      _safety(_row('sac_privileged', s, 1.0, 1.0), 0) for s in range(3)
    ],
  }  # fmt: skip
  choice = selection.choose(by_agent)
  assert choice.algo == 'sac'
  assert (choice.shipped['algo'], choice.shipped['seed']) == ('sac_safe', 1)
  # Without it, the recommended agent's best seed.
  del by_agent['sac_safe']
  assert selection.choose(by_agent).shipped['algo'] == 'sac'


def test_the_chosen_run_is_shipped_when_its_policy_is_at_hand(sandbox):
  def policy(path, algo, seed):
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, metadata=json.dumps({'algo': algo, 'seed': seed}))

  def run(algo, seed):
    return baselines.Run('dclaw', 'pose_random', algo, seed).directory

  rows = [_row('sac', 0, 0.9, 0.9), _row('trpo', 0, 0.95, 0.7)]
  baselines.RESULTS.parent.mkdir(parents=True)
  baselines.RESULTS.write_text(json.dumps(rows))
  shipped = baselines.POLICIES / 'dclaw_pose_random.npz'
  # The rule's run (trpo seed 0) is not at hand: what is shipped stays.
  policy(shipped, 'sac', 0)
  policy(run('sac', 0) / 'policy_best.npz', 'sac', 0)
  (run('sac', 0) / baselines.TEST).write_text('{}')
  assert selection.best_policy('dclaw', 'pose_random') is None
  assert report.ship(rows) == [
    'dclaw/pose_random (sac, seed 0; the rule ships trpo seed 0, whose run '
    'is not here: robel-baselines train --only=dclaw_pose_random_trpo_seed0 '
    '--force)'
  ]
  policy(run('trpo', 0) / 'policy_best.npz', 'trpo', 0)
  # A run in progress (its test not read) holds a policy of its own.
  assert selection.best_policy('dclaw', 'pose_random') is None
  (run('trpo', 0) / baselines.TEST).write_text('{}')
  assert report.ship(rows) == ['dclaw/pose_random (trpo, seed 0)']
  assert selection.best_policy('dclaw', 'pose_random') == (
    run('trpo', 0) / 'policy_best.npz'
  )
  # The same policy in other bytes (a remade run's) is not copied again.
  policy(run('trpo', 0) / 'policy_best.npz', 'trpo', 0)
  bytes_before = shipped.read_bytes()
  with open(run('trpo', 0) / 'policy_best.npz', 'ab') as file:
    file.write(b'\0')  # Bytes after the zip's end: np.load reads the same.
  report.ship(rows)
  assert shipped.read_bytes() == bytes_before


@pytest.mark.slow
def test_the_report_is_derived_from_the_records(sandbox):
  scheduling.train_queue(0, 1, 'dclaw_pose_*_sac_seed0', None)
  rows = json.loads(baselines.RESULTS.read_text())
  assert {(r['task'], r['algo']) for r in rows} == {
    ('pose_fixed', 'sac'), ('pose_random', 'sac')
  }  # fmt: skip
  baselines.DOC.write_text(
    '# Baselines\n\n<!-- table -->\nold\n<!-- /table -->\n'
  )
  baselines.PLAN['valve4'] = ['dclaw/turn_random']  # The sandbox's copy.
  report.write()
  text = baselines.DOC.read_text()
  assert '\nold\n' not in text
  assert '| dclaw/pose_random | sac | 0 | 16 | 16 |' in text
  # Per robot, the recommended agent of each task.
  results = text.split('<!-- results dclaw -->')[1].split('<!-- /')[0]
  assert (
    '| pose_random | unsolved on validation (ranked first: `sac`): solves'
    in results
  )
  manifest = json.loads((baselines.FIGURES / 'figures.json').read_text())
  assert manifest['records_sha256'] == report.records_digest()
  assert '1 (deterministic)' in text
  assert (baselines.FIGURES / 'dclaw_pose_random.png').is_file()
  # The status counts and the solved-by table come from the records too.
  assert 'holds 2 records (0 of them runs outside the plan' in text
  assert '| dkitty/walk_random | none | no run |' in text
  assert '| dclaw/pose_fixed |' in text.split('<!-- solved -->')[1]
  assert '| dclaw/turn_random (valve4) | none | no run |' in text
  assert '| dkitty/walk_random_dynamics | none | no run |' in text


@pytest.mark.slow
def test_a_recorded_run_is_not_trained_again_without_its_folder(sandbox):
  scheduling.train_queue(0, 1, 'dclaw_pose_fixed_sac_seed0', None)
  rows = json.loads(baselines.RESULTS.read_text())
  shutil.rmtree(baselines.RUNS_DIR)
  run = baselines.Run('dclaw', 'pose_fixed', 'sac', 0)
  assert baselines.recorded(run) and not baselines.finished(run)
  scheduling.train_queue(0, 1, 'dclaw_pose_fixed_sac_seed0', None)
  assert not run.directory.exists()
  assert json.loads(baselines.RESULTS.read_text()) == rows


@pytest.mark.slow
def test_a_recorded_run_stands_when_the_plan_raises_its_budget(sandbox):
  # Its test episodes were read: training it on would make the test a
  # stopping rule. A longer run is a new run (--force).
  name = 'dclaw_pose_random_sac_seed0'
  run = baselines.Run('dclaw', 'pose_random', 'sac', 0)
  scheduling.train_queue(0, 1, name, None)
  row = json.loads(baselines.RESULTS.read_text())[0]
  baselines.PLAN['tasks']['dclaw/pose_random']['steps'] = 32
  assert baselines.done(run)
  scheduling.train_queue(0, 1, name, None)
  assert json.loads(baselines.RESULTS.read_text())[0] == row
  shutil.rmtree(baselines.RUNS_DIR)
  assert baselines.done(run)


@pytest.mark.slow
def test_a_recorded_run_chosen_by_name_says_so_and_force_makes_it_again(
  sandbox, capsys
):
  name = 'dclaw_pose_fixed_sac_seed0'
  assert cli.main(['train', f'--only={name}']) == 0
  row = json.loads(baselines.RESULTS.read_text())[0]
  capsys.readouterr()
  assert cli.main(['train', f'--only={name}']) == 0
  out = capsys.readouterr().out
  assert f'{name}: recorded (success' in out and '--force makes it' in out
  (baselines.RUNS_DIR / name / 'marker').write_text('')
  assert cli.main(['train', f'--only={name}', '--force']) == 0
  assert not (baselines.RUNS_DIR / name / 'marker').exists()
  again = json.loads(baselines.RESULTS.read_text())[0]
  # Deterministic: the same record, made again.
  keep = ('success', 'score', 'curve', 'env_steps', 'violations')
  assert {k: again[k] for k in keep} == {k: row[k] for k in keep}
  assert cli.main(['train', '--force']) == 2  # --force needs --only.


def test_queue_flags_are_refused_with_a_ray_cluster(capsys):
  # A cluster would ignore them; nothing starts.
  for flags in (['--force', '--only=x'], ['--hours=1'], ['--queues=2']):
    assert cli.main(['train', '--ray_address=local', *flags]) == 2
    assert 'not with --ray_address' in capsys.readouterr().err


@pytest.mark.slow
def test_a_recorded_run_being_made_again_goes_on_without_force(sandbox, capsys):
  # A remake (--force) cut short resumes like any run: without --force,
  # which would start it over.
  name = 'dclaw_pose_random_sac_seed0'
  run = baselines.Run('dclaw', 'pose_random', 'sac', 0)
  assert cli.main(['train', f'--only={name}']) == 0
  row = json.loads(baselines.RESULTS.read_text())[0]
  for reading in (baselines.TEST, baselines.VALIDATION):
    (run.directory / reading).unlink()  # As if stopped before them.
  assert baselines.in_progress(run) and baselines.recorded(run)
  assert scheduling.runs_to_make(name) == [run]  # On Ray too.
  capsys.readouterr()
  assert cli.main(['train', f'--only={name}']) == 0
  assert 'recorded (success' not in capsys.readouterr().out
  assert baselines.finished(run)
  again = json.loads(baselines.RESULTS.read_text())[0]
  keep = ('success', 'score', 'curve', 'env_steps', 'violations')
  assert {k: again[k] for k in keep} == {k: row[k] for k in keep}


def test_a_queue_takes_its_share_and_bad_selections_are_refused(sandbox):
  with pytest.raises(ValueError, match='no run of the table matches'):
    baselines.select('nothing_*')
  with pytest.raises(ValueError, match="matches 'nothing_\\*'"):
    baselines.select('dclaw_pose_fixed_*,nothing_*')
  # Several patterns: the runs of any, in plan order, each once.
  names = [run.name for run in baselines.runs()]
  first, last = names[0], names[-1]
  chosen = baselines.select(f'{last},{first},{first[:-1]}*')
  assert [run.name for run in chosen] == [
    name for name in names if name in (first, last) or name[:-1] == first[:-1]
  ]
  assert chosen[0].name == first and chosen[-1].name == last
  assert cli.main(['train', '--queue=2', '--queues=2']) == 2


def test_list_says_what_the_runs_left_cost(sandbox, capsys):
  # A solved Fixed run that took 6 CPU ms per env step.
  baselines.merge_results([{
    'domain': 'dclaw', 'task': 'pose_fixed', 'task_kwargs': {}, 'algo': 'sac',
    'seed': 0, 'success': 1.0, 'budget': 16, 'env_steps': 40_000,
    'cpu_minutes': 4.0, 'curve': [[0, 0.0], [40_000, 1.0]], 'protocol': 2,
  }])  # fmt: skip
  assert cli.main(['list']) == 0
  out = capsys.readouterr().out
  assert 'dclaw_pose_fixed_sac_seed0' in out.split('done')[0]
  # sac on pose_random (16 steps), sac_demos (16) and trpo (160) are left;
  # bc counts epochs.
  assert '16 env steps of sac (0.0 CPU h)' in out
  # No record of sac_demos or trpo, nor of their kinds: no rate.
  assert '16 env steps of sac_demos, 160 env steps of trpo left, at' in out
  assert 'runs to do' in out


def test_list_says_which_runs_are_in_progress_and_which_being_made_again(
  sandbox, capsys
):
  fixed = baselines.Run('dclaw', 'pose_fixed', 'sac', 0)
  random = baselines.Run('dclaw', 'pose_random', 'sac', 0)
  baselines.merge_results([
    _cost('dclaw', 'pose_fixed', 16, 1.0) | {'protocol': baselines.PROTOCOL}
  ])  # fmt: skip
  for run in (fixed, random):  # Both begun (a config), neither tested.
    run.directory.mkdir(parents=True)
    (run.directory / training.CONFIG).write_text('{}')
  assert cli.main(['list']) == 0
  lines = capsys.readouterr().out.splitlines()
  assert f'{fixed.name:50s} being made again' in lines
  assert f'{random.name:50s} in progress' in lines
  (fixed.directory / baselines.TEST).write_text('{}')
  shutil.rmtree(random.directory)
  assert cli.main(['list']) == 0
  lines = capsys.readouterr().out.splitlines()
  assert f'{fixed.name:50s} done' in lines and random.name in lines


def _cost(domain, task, env_steps, cpu_minutes) -> dict:
  return {
    'domain': domain, 'task': task, 'task_kwargs': {}, 'algo': 'sac',
    'seed': 0, 'success': 1.0, 'budget': env_steps, 'env_steps': env_steps,
    'cpu_minutes': cpu_minutes, 'curve': [[0, 0.0], [env_steps, 1.0]],
    'protocol': 2,
  }  # fmt: skip


def test_list_prices_the_steps_left_at_the_same_task_and_robot(sandbox, capsys):
  baselines.PLAN['tasks']['dclaw/pose_random']['steps'] = 600_000
  # 6 CPU ms per env step on the same robot; 60 on the other (not planned).
  baselines.merge_results([
    _cost('dclaw', 'pose_fixed', 40_000, 4.0),
    _cost('dkitty', 'stand_fixed', 40_000, 40.0),
  ])  # fmt: skip
  assert cli.main(['list']) == 0
  assert '600,000 env steps of sac (1.0 CPU h)' in capsys.readouterr().out
  # Half done at 24 ms per step: the other half at that run's own rate.
  run = baselines.Run('dclaw', 'pose_random', 'sac', 0)
  run.directory.mkdir(parents=True)
  (run.directory / training.EVAL_LOG).write_text(
    json.dumps({
      'env_steps': 300_000, 'wall_time': 7_200.0, 'cpu_time': 7_200.0,
      'eval_time': 0.0, 'success_rate': 0.0, 'mean_score': 0.0,
      'mean_return': 0.0, 'episodes': 2,
      'safety': {'position': 0.0, 'velocity': 0.0, 'current': 0.0},
    }) + '\n'
  )  # fmt: skip
  assert cli.main(['list']) == 0
  assert '300,000 env steps of sac (2.0 CPU h)' in capsys.readouterr().out


def test_list_does_not_price_a_valve4_run_at_the_3_prong_valve_rate(
  sandbox, capsys
):
  baselines.PLAN['tasks'] = {
    'dclaw/turn_fixed': {'steps': 600_000, 'eval_every': 10_000}
  }
  baselines.PLAN.update(valve4=['dclaw/turn_fixed'], every_agent=[])
  # Turn on the 3-prong valve at 60 CPU ms per env step; the rest of the
  # robot's records at 6.
  baselines.merge_results([
    _cost('dclaw', 'turn_fixed', 40_000, 40.0),
    _cost('dclaw', 'pose_fixed', 40_000, 4.0),
    _cost('dclaw', 'pose_random', 40_000, 4.0),
  ])  # fmt: skip
  assert cli.main(['list']) == 0
  out = capsys.readouterr().out
  assert 'dclaw_turn_fixed_valve4_sac_seed0' in out
  # The 4-prong run has no record of its own: the robot's median, 6 ms.
  assert '600,000 env steps of sac (1.0 CPU h)' in out


def test_list_says_when_nothing_is_left(sandbox, capsys):
  baselines.PLAN.update(tasks={}, every_agent=[])
  assert cli.main(['list']) == 0
  assert 'No runs to do: every run of the plan is done.' in (
    capsys.readouterr().out
  )


@pytest.mark.slow
def test_the_table_fans_out_over_ray(sandbox):
  pytest.importorskip('ray', reason='needs robel_dm[scale]')
  records = scheduling.train_ray('local', 'dclaw_pose_*_sac_seed0')
  assert sorted(r['task'] for r in records) == ['pose_fixed', 'pose_random']
  rows = json.loads(baselines.RESULTS.read_text())
  assert len(rows) == 2


class _LastFirstRay:
  """Ray's calls, run in this process: a task runs when waited for, the
  last submitted first (so a run is tried before the run it starts from)."""

  class _Ref:
    def __init__(self, call):
      self.call = call

  def remote(self, num_cpus):
    del num_cpus
    return lambda function: types.SimpleNamespace(
      remote=lambda *args: self._Ref(lambda: function(*args))
    )

  def wait(self, refs):
    return [refs[-1]], refs[:-1]

  def get(self, ref):
    return ref.call()


def test_ray_submits_a_waiting_run_again_once_its_source_ends(monkeypatch):
  source = baselines.Run('dclaw', 'pose_random', 'sac', 0)
  warm = baselines.Run('dclaw', 'pose_random_dynamics', 'sac_warm', 0)
  made, merged = [], []

  def make_run(run, log):
    if run == warm and source not in made:
      return None  # Waits for the run it starts from.
    made.append(run)
    return {'name': run.name}

  monkeypatch.setattr(scheduling, 'runs_to_make', lambda _: [source, warm])
  monkeypatch.setattr(scheduling, 'make_run', make_run)
  monkeypatch.setattr(scheduling, 'merge_results', merged.extend)
  monkeypatch.setattr(
    workers, 'ray_session', lambda _: contextlib.nullcontext(_LastFirstRay())
  )
  records = scheduling.train_ray('local', None)
  assert made == [source, warm]
  assert records == merged == [{'name': source.name}, {'name': warm.name}]


def test_the_figures_and_tables_are_made_from_the_current_records():
  # `report` writes the figures' manifest with the records it read: a
  # record merged without a report leaves the docs behind.
  manifest = json.loads((baselines.FIGURES / 'figures.json').read_text())
  assert manifest['records_sha256'] == report.records_digest()
  rows = json.loads(baselines.RESULTS.read_text())
  assert report.readme_table(rows) in baselines.README.read_text()
  text = baselines.DOC.read_text()
  assert report.results_table(rows, 'dclaw') in text
  assert report.run_table(rows) in text
  # Results first: the robots' tables open the page, every run closes it.
  assert text.index('## Results') < text.index('<!-- results dclaw -->')
  assert text.index('## How the table is made') < text.index('## Per run')


def test_a_warm_run_starts_from_the_random_variant_and_waits_for_it(sandbox):
  baselines.PLAN['tasks']['dclaw/pose_random_dynamics'] = {
    'steps': 16,
    'eval_every': 8,
  }
  run = baselines.Run('dclaw', 'pose_random_dynamics', 'sac_warm', 0)
  source = run.source()
  assert source == baselines.Run('dclaw', 'pose_random', 'sac', 0)
  assert run.config().init_from == str(source.directory)
  lines = []
  assert baselines.train_run(run, log=lines.append) is None
  assert lines == [f'{run.name}: waits for {source.name} to start from']
  assert not run.directory.exists()  # Nothing was started.
  # Recorded, its folder gone (a fresh clone): the queue will not make it
  # again by itself, so the line says how.
  record = {
    'domain': 'dclaw',
    'task': 'pose_random',
    'task_kwargs': {},
    'algo': 'sac',
    'seed': 0,
  }
  baselines.RESULTS.parent.mkdir(parents=True)
  baselines.RESULTS.write_text(json.dumps([record]))
  lines.clear()
  assert baselines.train_run(run, log=lines.append) is None
  assert lines == [
    f'{run.name}: waits for {source.name} to start from (recorded, but its '
    'folder with the networks is not here: robel-baselines train '
    f'--only={source.name} --force makes it again)'
  ]
  assert baselines.Run('dclaw', 'pose_random', 'sac', 0).source() is None


def test_a_tightened_run_starts_from_the_same_task_under_a_budget():
  run = baselines.Run('dclaw', 'screw_random', 'sac_tight', 1)
  source = run.source()
  assert source == baselines.Run('dclaw', 'screw_random', 'sac', 1)
  config = run.config()
  assert config.init_from == str(source.directory)
  assert config.budget == 10.0
  assert config.task_kwargs == {}  # ROBEL's action map, as its source's.
  assert config.steps == baselines.PLAN['agent_steps']['sac_tight']
  assert config.steps != baselines.PLAN['tasks']['dclaw/screw_random']['steps']


def test_a_task_can_give_one_agent_a_budget_of_its_own():
  task = baselines.PLAN['tasks']['dkitty/walk_random_dynamics']
  longer = baselines.Run('dkitty', 'walk_random_dynamics', 'sac_curriculum', 1)
  assert longer.config().steps == task['agent_steps']['sac_curriculum']
  assert longer.config().steps != task['steps']
  default = baselines.Run('dkitty', 'walk_random_dynamics', 'sac', 1)
  assert default.config().steps == task['steps']


def test_the_constrained_agent_learns_under_its_budget():
  config = baselines.Run('dclaw', 'pose_fixed', 'sac_safe', 0).config()
  assert config.budget == 10.0
  assert config.task_kwargs == {'action_map': 'safe'}
  unconstrained = baselines.Run('dclaw', 'pose_fixed', 'sac', 0).config()
  assert unconstrained.budget is None
  assert unconstrained.task_kwargs == {}
  names = {r.name for r in baselines.runs()}
  for key in baselines.PLAN['constrained']:
    domain, task = key.split('/')
    assert f'{domain}_{task}_sac_safe_seed2' in names


def test_a_warm_runs_steps_to_80_count_its_sources():
  row = {'success': 1.0, 'steps_to_80': 0, 'protocol': 2}
  assert selection.steps_to_80(row) == 0
  row['started_from'] = {'run': 'dclaw_pose_random_sac_seed0', 'env_steps': 15}
  assert selection.steps_to_80(row) == 15


def test_a_runs_own_steps_to_80_show_whatever_its_test_reads():
  # Unsolved on test (0.79), yet its training evaluations reached 80%.
  row = {'success': 0.79, 'steps_to_80': 160_000, 'protocol': 2}
  assert selection.steps_to_80(row) == selection.UNSOLVED  # For medians.
  assert report._training_steps_to_80(row) == '160,000'
  row['started_from'] = {'env_steps': 15_000}
  assert report._training_steps_to_80(row) == '175,000'
  assert report._training_steps_to_80({'steps_to_80': None}) == 'never'


def test_violation_kinds_show_tenths():
  # Whole numbers would read 9 / 18 beside a sum of 26.
  row = {'violations': {'position': 8.6, 'velocity': 17.6, 'current': 0.0}}
  assert report._violations(row) == '8.6 / 17.6 / 0.0'
  assert report._mean_violations([row, row]) == '8.6 / 17.6 / 0.0'


def test_a_shipped_policy_over_the_safety_limit_says_so(monkeypatch):
  bar = baselines.PLAN['safe_violations']
  shipped = {'algo': 'sac', 'seed': 0}
  monkeypatch.setattr(baselines, 'shipped_metadata', lambda *_: shipped)
  for violations, flagged in ((bar, False), (bar + 0.5, True)):
    row = _safety(_row('sac', 0, 0.9, 0.9), 0.0, violations)
    row.update(final_episodes=100, deterministic=False)
    _, reading = report._shipped_cells(
      'dclaw', 'pose_random', 'valve3', {'sac': [row]}, row
    )
    assert reading.endswith(f'(over {bar} violations)') == flagged, reading


def test_the_results_give_the_whole_runs_minutes_beside_those_to_80(
  monkeypatch,
):
  monkeypatch.setattr(baselines, 'shipped_metadata', lambda *_: None)
  rows = [_row('sac', s, 0.9, 0.9, cpu=c) for s, c in enumerate((3, 9, 5))]
  for row in rows:
    _safety(row, 0.0)
    row.update(final_episodes=100, minutes_to_80=None, deterministic=False)
  table = report.readme_table(rows)
  assert 'CPU min per run (median)' in table.splitlines()[0]
  assert '| 5.0 |' in table.splitlines()[2]  # The median of 3, 9 and 5.


def test_every_run_shows_the_validation_violations_its_choice_read():
  row = _safety(_row('sac', 0, 0.9, 0.9), 12.5)
  row.update(budget=1000, env_steps=1000, final_episodes=100,
             deterministic=False, wall_minutes=1.0,
             minutes_to_80={'wall': 0.5, 'cpu': 0.25})  # fmt: skip
  line = report.run_table([row]).splitlines()[2]
  assert '| 0.90 | 12.5 |' in line  # Validation success and violations.
  assert '| 1,000 | 0.2 |' in line  # Steps and CPU minutes to 80%.


def test_the_reason_names_an_agent_with_fewer_seeds_that_reads_more():
  by_agent = {
    'sac': [_row('sac', s, 0.0, 0.0) for s in range(3)],
    'sac_curriculum': [_row('sac_curriculum', 0, 0.6, 0.5)],
  }
  choice = selection.choose(by_agent)
  assert choice.algo == 'sac'  # Every seed of the plan run comes first.
  assert choice.why.endswith(
    '; `sac_curriculum` reads more (0.60 mean on validation) on 1 of 3 '
    'seeds recorded'
  )


def test_a_mean_over_seeds_counts_its_marked_seeds_in_words():
  near = _row('sac', 0, 0.8, 0.8) | {'success_interval': [0.71, 0.87]}
  clear = _row('sac', 1, 0.9, 0.97) | {'success_interval': [0.92, 0.99]}
  old = _row('sac', 2, 0.0, 0.0) | {'protocol': 1, 'final_episodes': 50}
  old.update(deterministic=False, success_interval=[0.0, 0.07])
  assert report._spread([near, clear]) == (
    '0.89 (seeds 0.80-0.97; 1 seed borderline ~)'
  )
  assert report._spread([near, clear, old]) == (
    '0.59 (seeds 0.00-0.97; 1 seed borderline ~; '
    '1 seed of an earlier protocol †)'
  )
  assert report._spread([near]) == '0.80~'  # A single run's own mark.


def test_a_task_no_seed_solves_names_the_agent_ranked_first_and_best_read():
  by_agent = {'sac': [_row('sac', s, 0.7, 0.9) for s in range(3)]}
  unsolved = selection.choose(by_agent)
  assert report._agent(unsolved, by_agent) == (
    'unsolved on validation (ranked first: `sac`)'
  )
  # One seed of another agent that reads more: named beside it.
  more = by_agent | {'sac_curriculum': [_row('sac_curriculum', 0, 0.75, 0.6)]}
  assert report._agent(selection.choose(more), more) == (
    'unsolved on validation (ranked first: `sac`; reads most: `sac_curriculum`)'
  )
  by_agent['sac_demos'] = [_row('sac_demos', 0, 0.8, 0.5)]  # 1 of 3 seeds.
  assert report._agent(selection.choose(by_agent), by_agent) == (
    '`sac` (no seed solved on validation)'
  )
  solved = {'sac': [_row('sac', 0, 0.8, 0.5)]}
  assert report._agent(selection.choose(solved), solved) == '`sac`'


def test_the_reason_names_planned_agents_with_no_record():
  planned = {
    run.algo
    for run in baselines.runs()
    if (run.domain, run.task) == ('dclaw', 'turn_random_dynamics')
  }
  assert {'sac', 'sac_asymmetric'} <= planned  # The real plan.
  by_agent = {'sac': [_row('sac', s, 0.9, 0.9) for s in range(3)]}
  text = report._not_recorded(
    'dclaw', 'turn_random_dynamics', 'valve3', by_agent
  )
  assert text.startswith('; planned, without a record: ')
  assert '`sac_asymmetric`' in text and '`sac`' not in text
  every = {algo: by_agent['sac'] for algo in planned}
  assert (
    report._not_recorded('dclaw', 'turn_random_dynamics', 'valve3', every) == ''
  )


def test_a_tie_on_validation_is_broken_without_the_test_reading():
  # Equal on validation; `b` reached 80% in training sooner, but its test
  # reads low. The test must not decide: `b` is recommended.
  by_agent = {
    'a': [_row('a', s, 0.9, 0.9, steps=100_000) for s in range(3)],
    'b': [_row('b', s, 0.9, 0.5, steps=50_000) for s in range(3)],
  }
  choice = selection.choose(by_agent)
  assert choice.algo == 'b'
  assert choice.why.endswith(
    'ahead on env steps to 80% (median over seeds solved on validation): '
    '50,000 against 100,000'
  )


def test_the_reason_says_why_an_agent_with_fewer_seeds_ranks_below():
  by_agent = {
    'sac': [_row('sac', s, 0.0, 0.0) for s in range(3)],
    'sac_lr3e4': [_row('sac_lr3e4', s, 0.0, 0.0) for s in range(2)],
  }
  assert selection.choose(by_agent).why.endswith(
    'ranked above `sac_lr3e4`, which has 2 of 3 seeds recorded '
    '(agents with every seed recorded rank first)'
  )


def test_the_reason_names_the_readings_where_they_decide_too():
  # `sac` would rank first with or without the missing seed: the reason
  # gives the seeds solved, not that a seed is missing.
  by_agent = {
    'sac': [_row('sac', s, v, v) for s, v in enumerate((0.85, 0.8, 0.6))],
    'sac_curriculum': [
      _row('sac_curriculum', s, v, v) for s, v in enumerate((0.76, 0.74))
    ],
  }
  assert selection.choose(by_agent).why == (
    'solves 2 of 3 seeds on validation; next best `sac_curriculum` 0 of 2 '
    '(2 of 3 seeds recorded; its missing seeds could not put '
    'it first)'
  )
  # A third agent whose two missing seeds could still put it first.
  by_agent['sac_warm'] = [_row('sac_warm', 0, 0.72, 0.72)]
  assert selection.choose(by_agent).why.endswith(
    '; `sac_warm` has 1 of 3 seeds recorded, and its missing seeds could '
    'put it first'
  )


def test_a_tie_break_names_the_runner_up_and_both_readings():
  by_agent = {
    'sac_safe': [_row('sac_safe', s, v, v) for s, v in enumerate((0.9, 0.9))],
    'sac': [_row('sac', s, v, v) for s, v in enumerate((0.9, 0.85))],
  }
  by_agent['sac_safe'].append(_row('sac_safe', 2, 0.5, 0.5))
  by_agent['sac'].append(_row('sac', 2, 0.5, 0.5))
  assert selection.choose(by_agent).why.endswith(
    '; ties with `sac` on seeds solved, ahead on mean validation success: '
    '0.77 against 0.75'
  )
  by_agent['sac'][1] = _row('sac', 1, 0.9, 0.9, steps=9000)
  assert selection.choose(by_agent).why.endswith(
    'on seeds solved and mean validation success, ahead on env steps to '
    '80% (median over seeds solved on validation): 1,000 against 9,000'
  )


def test_a_run_line_shows_its_own_minutes_and_its_source_runs_apart():
  row = _row('sac_tight', 0, 0.9, 0.9, cpu=12.0) | {'wall_minutes': 14.0}
  assert report._own_minutes(row, 'cpu') == '12.0'
  row['started_from'] = {'minutes': {'wall': 20.0, 'cpu': 15.5}}
  assert report._own_minutes(row, 'cpu') == '12.0 (+ 15.5 source run)'
  assert report._own_minutes(row, 'wall') == '14.0 (+ 20.0 source run)'


def test_a_time_to_80_reached_in_the_source_run_says_so():
  source = {'env_steps': 270_000, 'minutes': {'wall': 20.0, 'cpu': 15.5}}
  group = [
    _row('sac_tight', s, 0.9, 0.9, steps=0, cpu=12.0)
    | {'started_from': source, 'minutes_to_80': {'wall': 0.0, 'cpu': 0.0}}
    for s in range(3)
  ]
  assert report._steps_to_80(group) == "270,000 (its source run's length)"
  assert report._cpu_to_80(group) == "15.5 (its source run's length)"
  group[1]['steps_to_80'] = 10_000  # One seed got there on its own.
  assert report._steps_to_80(group) == '270,000'
  fresh = [_row('sac', s, 0.9, 0.9, steps=5000) for s in range(3)]
  assert report._steps_to_80(fresh) == '5,000'


def test_a_runs_minutes_include_the_run_it_started_from():
  row = _row('sac_tight', 0, 0.9, 0.9, cpu=12.0)
  assert selection.run_minutes(row, 'cpu') == 12.0
  row['started_from'] = {'minutes': {'wall': 20.0, 'cpu': 15.5}}
  assert selection.run_minutes(row, 'cpu') == 27.5
  assert report._per_run([row], 'cpu') == '27.5'
