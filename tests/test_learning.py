"""The learning path: Gymnasium adapter, training, numpy policies, evaluation.

The adapter tests need Gymnasium; training and the numpy-equals-torch
comparison need the `learn` extra (Stable-Baselines3 and torch).
"""

import json
import pathlib

import numpy as np
import pytest
from scipy import stats

gymnasium = pytest.importorskip('gymnasium', reason='needs robel_dm[learn]')
from gymnasium.utils import env_checker  # noqa: E402

from robel_dm import assets, evaluation, policies, suite  # noqa: E402
from robel_dm.learning import baselines  # noqa: E402
from robel_dm.learning import gym as robel_gym  # noqa: E402
from robel_dm.learning.baselines import selection  # noqa: E402

_IDS = robel_gym.env_ids()
# ROBEL's flat observation sizes per family.
_SIZES = {'pose': 27, 'turn': 21, 'screw': 21, 'stand': 61, 'orient': 53,
          'walk': 52}  # fmt: skip


def test_every_task_and_valve4_variant_has_robels_name():
  names = {env_id.split('/')[1] for env_id in _IDS}
  assert len(_IDS) == len(suite.ALL_TASKS) + 6
  assert {
    'DClawPoseFixed-v0',
    'DClawTurnRandomDynamics-v0',
    'DKittyWalkRandomDynamics-v0',
    'DClawScrewFixedValve4-v0',
  } <= names
  assert all(env_id in gymnasium.envs.registry for env_id in _IDS)


@pytest.mark.slow
@pytest.mark.parametrize('env_id', sorted(_IDS))
def test_adapter_conforms_and_keeps_signals_out_of_the_observation(env_id):
  env = gymnasium.make(env_id)
  try:
    env_checker.check_env(env.unwrapped, skip_render_check=True)
    domain, task, task_kwargs = _IDS[env_id]
    assert env.unwrapped.task_kwargs == task_kwargs
    family = task.split('_')[0]
    assert env.observation_space.shape == (_SIZES[family],)
    assert env.observation_space.dtype == np.float32
    assert env.action_space.dtype == np.float32
    assert (env.action_space.low == -1).all() and (
      env.action_space.high == 1
    ).all()
    observation, info = env.reset(seed=3)
    assert set(info) == {'score', 'success', 'safety', 'reward_terms'}
    assert set(info['safety']) == {'position', 'velocity', 'current'}
    unwrapped = env.unwrapped
    # The observation is exactly ROBEL's agent vector, nothing else.
    flat = unwrapped.robel_env.task.flatten_observation(
      unwrapped._timestep.observation  # noqa: SLF001
    )
    np.testing.assert_array_equal(observation, flat.astype(np.float32))
  finally:
    env.close()


@pytest.mark.slow
def test_seeded_resets_reproduce():
  env = gymnasium.make('robel_dm/DClawTurnRandom-v0')
  first, _ = env.reset(seed=5)
  env.step(env.action_space.sample())
  again, _ = env.reset(seed=5)
  other, _ = env.reset(seed=6)
  np.testing.assert_array_equal(first, again)
  assert not np.array_equal(first, other)
  env.close()


@pytest.mark.slow
def test_time_limit_truncates_and_a_fall_terminates():
  env = gymnasium.make('robel_dm/DClawPoseFixed-v0')
  env.reset(seed=0)
  steps, terminated, truncated = 0, False, False
  while not (terminated or truncated):
    _, _, terminated, truncated, _ = env.step(np.zeros(9, np.float32))
    steps += 1
  assert truncated and not terminated and steps == 80
  env.close()
  kitty = gymnasium.make('robel_dm/DKittyWalkFixed-v0')
  kitty.reset(seed=0)
  rng = np.random.default_rng(0)
  for _ in range(160):
    _, _, terminated, truncated, _ = kitty.step(
      rng.uniform(-1, 1, 12).astype(np.float32)
    )
    if terminated or truncated:
      break
  assert terminated and not truncated  # Random actions topple it.
  kitty.close()


def test_suite_arguments_pass_through():
  env = gymnasium.make(
    'robel_dm/DClawTurnFixed-v0',
    task_kwargs={'observation_keys': ('claw_qpos', 'target_error')},
    time_limit=1.0,
  )
  observation, _ = env.reset(seed=0)
  assert observation.shape == (10,)
  steps = 0
  while True:
    _, _, terminated, truncated, _ = env.step(np.zeros(9, np.float32))
    steps += 1
    if terminated or truncated:
      break
  assert steps == 10
  env.close()


@pytest.mark.slow
def test_async_vector_env_runs_the_tasks():
  envs = gymnasium.vector.AsyncVectorEnv(
    [lambda: gymnasium.make('robel_dm/DClawPoseFixed-v0')] * 2
  )
  try:
    observations, _ = envs.reset(seed=[0, 1])
    assert observations.shape == (2, 27)
    observations, rewards, *_ = envs.step(envs.action_space.sample())
    assert rewards.shape == (2,)
  finally:
    envs.close()


# --- Policies without torch ---------------------------------------------------


def _tiny_policy(tmp_path, task='pose_fixed', keys=None) -> pathlib.Path:
  rng = np.random.default_rng(0)
  keys = keys or ('qpos', 'last_action', 'qpos_error')
  policy = policies.NumpyPolicy(
    [rng.normal(size=(8, 27)), rng.normal(size=(9, 8))],
    [rng.normal(size=8), rng.normal(size=9)],
    'relu',
    'tanh',
    {
      'domain': 'dclaw',
      'task': task,
      'task_kwargs': {},
      'observation_keys': list(keys),
      'algo': 'sac',
      'seed': 3,
    },  # fmt: skip
  )
  path = tmp_path / 'policy.npz'
  policy.save(path)
  return path


@pytest.mark.slow
def test_numpy_policy_round_trips_and_evaluates(tmp_path):
  path = _tiny_policy(tmp_path)
  policy = policies.load(path)
  # Recordings name their policy by this: the run, seed included.
  assert repr(policy) == 'NumpyPolicy(sac seed 3 on dclaw/pose_fixed)'
  results = evaluation.evaluate(
    evaluation.EvalConfig('dclaw', 'pose_fixed', 2, policy=str(path))
  )
  assert results['episodes'] == 2
  env = suite.load('dclaw', 'pose_fixed', seed=0)
  timestep = env.reset()
  action = policy(timestep)
  assert action.shape == (9,) and np.all(np.abs(action) <= 1)
  env.close()


def test_policy_errors_are_clear(tmp_path):
  with pytest.raises(policies.PolicyError, match='no policy file'):
    evaluation.evaluate(
      evaluation.EvalConfig(
        'dclaw', 'pose_fixed', 1, policy=str(tmp_path / 'x.npz')
      )
    )
  path = _tiny_policy(tmp_path)
  with pytest.raises(policies.PolicyError, match='trained on dclaw/pose_fixed'):
    evaluation.evaluate(
      evaluation.EvalConfig('dclaw', 'turn_fixed', 1, policy=str(path))
    )
  # A task with no shipped policy (the table ships one per solved task).
  unshipped = next(
    (domain, task)
    for domain, task in suite.ALL_TASKS
    if not (assets.baselines_dir() / f'{domain}_{task}.npz').is_file()
  )
  with pytest.raises(policies.PolicyError, match='no baseline policy'):
    evaluation.evaluate(evaluation.EvalConfig(*unshipped, 1, policy='baseline'))
  bad = tmp_path / 'bad.npz'
  np.savez(bad, something=np.zeros(3))
  with pytest.raises(policies.PolicyError, match='not a robel_dm policy'):
    policies.load(bad)


@pytest.mark.slow
def test_saved_policy_runs_on_the_virtual_bus(tmp_path):
  pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
  path = _tiny_policy(tmp_path)
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw',
      'pose_fixed',
      1,
      policy=str(path),
      robot=suite.RobotOptions('virtual'),
    )
  )
  assert results['episodes'] == 1 and results['device_path'] == 'virtual'


# Training runs are tested in test_training.py.


# --- Shipped baselines --------------------------------------------------------

_SHIPPED = sorted(
  tuple(path.stem.split('_', 1))
  for path in pathlib.Path(__file__)
  .resolve()
  .parents[1]
  .joinpath('policies')
  .glob('*.npz')
)


def _shipped_row(domain: str, task: str) -> dict:
  """The table's row that a shipped policy's metadata names."""
  metadata = baselines.shipped_metadata(domain, task)
  rows = json.loads(baselines.RESULTS.read_text())
  (row,) = (
    row
    for row in rows
    if (row['domain'], row['task'], row['algo'], row['seed'])
    == (domain, task, metadata['algo'], metadata['seed'])
    and row['task_kwargs'] == metadata['task_kwargs']
  )
  return row


def test_every_task_solved_on_validation_ships_a_policy():
  # Shipping reads validation episodes, as every decision does (a test
  # reading decides nothing); a policy whose actor observes what only a
  # simulation knows never ships.
  rows = json.loads(baselines.RESULTS.read_text())
  solved = {
    (row['domain'], row['task'])
    for row in rows
    if 'valve' not in row['task_kwargs']
    and selection.for_robots(row['algo'])
    and selection.validation_success(row) >= baselines.PLAN['solved']
  }
  assert set(_SHIPPED) == solved


@pytest.mark.slow
@pytest.mark.parametrize(
  'shipped', _SHIPPED, ids=['/'.join(t) for t in _SHIPPED]
)
def test_shipped_baselines_reproduce_their_rows(shipped):
  # From seeds neither training nor the table's evaluations used. A Fixed
  # task's episodes are all the same one: one episode is the whole test.
  # A Random task's policy gets as many fresh episodes as its row's final
  # evaluation, and fails if they succeed significantly less often than
  # the row's (one-sided Fisher exact test at the 1% level).
  row = _shipped_row(*shipped)
  # Shipping reads validation; a seed solved there can read under 0.8 on
  # its test episodes (a borderline row).
  assert selection.solved_on_validation(row)
  if shipped in suite.FIXED:
    results = evaluation.evaluate(
      evaluation.EvalConfig(*shipped, 1, policy='baseline', seed=5_000_000)
    )
    assert results['success_rate'] == 1.0
    return
  episodes = row['final_episodes']
  results = evaluation.evaluate(
    evaluation.EvalConfig(*shipped, episodes, policy='baseline', seed=5_000_000)
  )
  fresh = round(results['success_rate'] * episodes)
  recorded = round(row['success'] * episodes)
  table = [[fresh, episodes - fresh], [recorded, episodes - recorded]]
  assert stats.fisher_exact(table, alternative='less').pvalue >= 0.01


@pytest.mark.slow
def test_the_pose_baseline_runs_on_the_virtual_bus():
  pytest.importorskip('dynamixel_sdk', reason='needs robel_dm[hardware]')
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw',
      'pose_fixed',
      1,
      policy='baseline',
      robot=suite.RobotOptions('virtual'),
    )
  )
  assert results['success_rate'] == 1.0
