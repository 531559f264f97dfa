"""The benchmark scripts import, and their printed verdicts say the right thing.

The benchmarks themselves take minutes to hours and are run by hand; these
tests catch what would otherwise surface only then: a script whose imports
no longer resolve, a ratio printed as a plain number when it is a bound, a
candidate setting the agent's library does not accept.
"""

import importlib
import inspect
import pathlib

import pytest

_BENCHMARKS = pathlib.Path(__file__).resolve().parents[1] / 'benchmarks'
_SCRIPTS = sorted(path.stem for path in _BENCHMARKS.glob('*.py'))


@pytest.fixture
def benchmarks(monkeypatch):
  """Imports a benchmark script as its own `python benchmarks/X.py` would."""
  monkeypatch.syspath_prepend(str(_BENCHMARKS))
  return importlib.import_module


@pytest.mark.parametrize('name', _SCRIPTS)
def test_every_script_imports_and_has_a_main(benchmarks, name):
  module = benchmarks(name)
  assert callable(module.main)
  # argparse's description is the docstring's first line.
  assert module.__doc__.strip().splitlines()[0]


def _row(algo, solved, train, whole=None, steps=10_000):
  return {
    'task': 'turn_fixed',
    'seed': 1,
    'algo': algo,
    'solved': solved,
    'env_steps': steps,
    'train_seconds': train,
    'cpu_seconds': train,
    'whole_seconds': whole or train + 10,
  }


@pytest.mark.parametrize(
  'sb3_solved, ours_solved, verdict',
  [
    (True, True, 'turn_fixed seed 1: 5.0x (4.2x)'),
    # SB3's SAC unsolved: its time to 80% is longer than it ran.
    (False, True, 'turn_fixed seed 1: >5.0x (>4.2x)'),
    # The default unsolved: its time to 80% is longer, the ratio smaller.
    (True, False, 'turn_fixed seed 1: <5.0x (<4.2x) (sac unsolved'),
    (False, False, 'turn_fixed seed 1: neither reached 80%'),
  ],
)
def test_speed_ratio_is_a_bound_when_one_agent_is_unsolved(
  benchmarks, capsys, sb3_solved, ours_solved, verdict
):
  training_speed = benchmarks('training_speed')
  training_speed.print_results(
    [
      _row('sac_sb3', sb3_solved, train=500, whole=540),
      _row('sac', ours_solved, train=100, whole=130),
    ]
  )
  (line,) = [
    line for line in capsys.readouterr().out.splitlines()
    if line.startswith('  turn_fixed seed 1:')
  ]  # fmt: skip
  assert line.strip().startswith(verdict)


def test_every_candidate_setting_is_accepted_by_the_agent(benchmarks):
  sbx = pytest.importorskip('sbx', reason='needs robel_dm[learn]')
  agent_settings = benchmarks('agent_settings')
  accepted = set(inspect.signature(sbx.SAC.__init__).parameters)
  for name, (hidden, hyperparameters) in agent_settings.SETTINGS.items():
    assert set(hyperparameters) <= accepted, name
    assert all(isinstance(width, int) for width in hidden), name


@pytest.mark.parametrize(
  'domain, family, alone',
  [
    ('dclaw', 'pose', {'damping', 'friction_loss', 'gain'}),
    ('dclaw', 'turn', {'damping', 'friction_loss', 'gain',
                       'contact_friction', 'mount'}),
    ('dkitty', 'walk', {'damping', 'friction_loss', 'gain',
                        'contact_friction', 'mass', 'terrain'}),
  ],
)  # fmt: skip
def test_randomdynamics_parts_takes_the_task_apart(
  benchmarks, domain, family, alone
):
  from robel_dm import suite  # noqa: PLC0415

  parts = benchmarks('randomdynamics_parts')
  task = suite.load(domain, f'{family}_random_dynamics').task
  table = parts.conditions(task.dynamics, terrain=domain == 'dkitty')
  assert set(table) == {'plain', 'noise', 'dynamics', 'all'} | alone
  # 'all' is the RandomDynamics task: its ranges, noise and terrain.
  every = suite.load(domain, f'{family}_random', task_kwargs=table['all'])
  assert every.task.dynamics == task.dynamics
  assert every.task.observation_noise == task.observation_noise
  assert every.task.arena.has_terrain if domain == 'dkitty' else True
  # A quantity alone randomizes that quantity and nothing else.
  gain = table['gain']['dynamics']
  assert gain.actuator_kp == task.dynamics.actuator_kp
  assert gain.damping is None and gain.geom_friction is None


def test_randomdynamics_draws_splits_the_episodes_by_what_was_drawn(
  benchmarks,
):
  from robel_dm import suite  # noqa: PLC0415

  draws = benchmarks('randomdynamics_draws')
  rows = [{'draws': {'q': value}} for value in (5.0, 1.0, 3.0, 2.0, 4.0, 6.0)]
  assert draws.thirds(rows, 'q') == [
    'high', 'low', 'middle', 'low', 'middle', 'high'
  ]  # fmt: skip
  # Episodes 1 and 3 fail under both policies; failing independently,
  # half of the four (1/2 x 1 failure rates) would.
  results = {
    name: [{'success': s} for s in successes]
    for name, successes in (('a', [1, 0, 1, 0]), ('b', [0, 0, 0, 0]))
  }
  assert draws._unsolved(results) == (
    'solved by no policy: 2 of 4 episodes '
    '(if the policies failed independently: 2.0)'
  )
  rows = [
    {'success': False, 'ended_early': True, 'final_score': 0.1},
    {'success': False, 'ended_early': False, 'final_score': 0.6},
    {'success': False, 'ended_early': False, 'final_score': 0.8},
    {'success': True, 'ended_early': False, 'final_score': 1.0},
  ]
  assert draws._failures({'a': rows}).endswith('policy 0 3 (1 early, 0.700)')
  env = suite.load('dkitty', 'orient_random_dynamics', seed=4)
  timestep = env.reset()
  drawn = draws.drawn(env)
  physics = env.task.dynamics_draws
  assert drawn['damping'] == physics['damping'][0]
  assert [drawn[f'geom_friction.{p}'] for p in ('slide', 'spin', 'roll')] == (
    physics['geom_friction'].tolist()
  )
  # The angle to turn: the reset's score.
  assert drawn['score_at_reset'] == float(timestep.observation['score'])
  assert -1.0 <= drawn['terrain.mean'] <= 1.0
  assert 0.0 < drawn['terrain.spread'] <= 2.0
  env.close()


@pytest.mark.slow
def test_update_cost_times_each_agents_own_update_step(benchmarks):
  import argparse  # noqa: PLC0415

  module = benchmarks('update_cost')
  args = argparse.Namespace(transitions=200, warmup=1, calls=1)
  sac, droq = (module.measure(name, args) for name in ('sac', 'droq'))
  # Per env step: the agent's updates per step times one update's cost.
  assert sac['updates_per_env_step'] == 1 and droq['updates_per_env_step'] == 10
  assert droq['cpu_ms_per_env_step'] == pytest.approx(
    10 * droq['cpu_ms_per_update']
  )
  assert sac['batch_size'] == droq['batch_size'] == 128
  assert sac['cpu_ms_per_update'] > 0
