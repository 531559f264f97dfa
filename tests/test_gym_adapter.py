"""The Gymnasium adapter's edges: actions, import orders, episode ends.

* The adapter accepts and rejects exactly the actions the robel_dm
  environment does, with the same error, and rejects them before the
  environment sees them.
* Every documented way to make an id works in any import order, and
  `import robel_dm` alone imports neither gymnasium nor the suite.
* `step` before the first `reset` or after the end of an episode raises a
  clear error instead of failing inside the adapter.
"""

import subprocess
import sys
import textwrap
from unittest import mock

import numpy as np
import pytest

gymnasium = pytest.importorskip('gymnasium', reason='needs robel_dm[learn]')

from robel_dm import suite  # noqa: E402
from robel_dm.learning import gym as robel_gym  # noqa: E402

_TASK = ('dclaw', 'pose_fixed')
_NUM_ACTIONS = 9

# What `suite.load` environments reject, each for its own reason.
_BAD_ACTIONS = {
  'complex': np.full(_NUM_ACTIONS, 0.1 + 1j),
  'complex_without_imaginary_part': np.full(_NUM_ACTIONS, 0.1 + 0j),
  'numeric_strings': ['0.1'] * _NUM_ACTIONS,
  'string_array': np.full(_NUM_ACTIONS, '0.1'),
  'bytes': np.full(_NUM_ACTIONS, b'0.1'),
  'one_string_among_numbers': [0.1] * (_NUM_ACTIONS - 1) + ['0.1'],
  'objects': np.full(_NUM_ACTIONS, 0.1, dtype=object),
  'none': None,
  'timedeltas': np.zeros(_NUM_ACTIONS, 'timedelta64[s]'),
  'too_short': np.zeros(_NUM_ACTIONS - 1),
  'too_long': np.zeros(_NUM_ACTIONS + 1),
  'column': np.zeros((_NUM_ACTIONS, 1)),
  'scalar': 0.0,
  'empty': [],
  'ragged': [[0.1] * _NUM_ACTIONS, [0.1]],
  'nan': np.full(_NUM_ACTIONS, np.nan),
  'one_inf': [0.0] * (_NUM_ACTIONS - 1) + [np.inf],
  'above_one': np.full(_NUM_ACTIONS, 1.5),
  'below_minus_one_int': np.full(_NUM_ACTIONS, -2),
  'just_above_one_float32': np.full(_NUM_ACTIONS, 1.01, np.float32),
}

# What they accept (the last one within the bound's rounding tolerance).
_GOOD_ACTIONS = {
  'float64': np.full(_NUM_ACTIONS, 0.3),
  'float32': np.full(_NUM_ACTIONS, -0.3, np.float32),
  'ints': [1, 0, -1] * 3,
  'bools': np.ones(_NUM_ACTIONS, bool),
  'tuple': (0.2,) * _NUM_ACTIONS,
  'rounding_above_one': np.full(_NUM_ACTIONS, 1 + 1e-7),
}


@pytest.fixture(scope='module')
def adapter():
  env = robel_gym.RobelEnv(*_TASK, seed=0)
  env.reset(seed=0)
  yield env
  env.close()


def _error(call) -> str:
  with pytest.raises(ValueError) as info:
    call()
  return str(info.value)


# --- Actions ------------------------------------------------------------------


@pytest.mark.parametrize('action', _BAD_ACTIONS.values(), ids=_BAD_ACTIONS)
def test_adapter_rejects_what_the_environment_rejects_before_stepping(
  action, adapter, shared_env, monkeypatch
):
  env = shared_env(_TASK)
  env.reset()
  expected = _error(lambda: env.step(action))
  step = mock.Mock(wraps=adapter.robel_env.step)
  monkeypatch.setattr(adapter.robel_env, 'step', step)
  assert _error(lambda: adapter.step(action)) == expected
  assert '\n' not in expected
  step.assert_not_called()


@pytest.mark.parametrize('action', _GOOD_ACTIONS.values(), ids=_GOOD_ACTIONS)
def test_adapter_accepts_what_the_environment_accepts_with_same_targets(
  action, adapter, shared_env
):
  env = shared_env(_TASK)
  env.reset()
  env.step(action)
  adapter.reset(seed=0)
  adapter.step(action)
  np.testing.assert_array_equal(
    adapter.robel_env.physics.data.ctrl, env.physics.data.ctrl
  )


@pytest.mark.slow
def test_clipping_tasks_clip_in_the_adapter_too():
  kwargs = {'action_bounds': 'clip'}
  env = suite.load(*_TASK, task_kwargs=kwargs, seed=0)
  adapter = robel_gym.RobelEnv(*_TASK, task_kwargs=kwargs, seed=0)
  try:
    env.reset()
    adapter.reset(seed=0)
    action = np.array([1.5, -3, 0.5] * 3)
    env.step(action)
    adapter.step(action)
    np.testing.assert_array_equal(
      adapter.robel_env.physics.data.ctrl, env.physics.data.ctrl
    )
  finally:
    env.close()
    adapter.close()


# --- Import orders ------------------------------------------------------------

_MAKE = """
env = gymnasium.make({env_id!r})
observation, _ = env.reset(seed=0)
env.step(env.action_space.sample())
assert observation.shape == (21,), observation.shape
env.close()
"""
_IMPORT_ORDERS = {
  'robel_dm_then_gymnasium_prefixed': (
    'import robel_dm\nimport gymnasium',
    'robel_dm:robel_dm/DClawTurnFixed-v0',
  ),
  'robel_dm_then_gymnasium': (
    'import robel_dm\nimport gymnasium',
    'robel_dm/DClawTurnFixed-v0',
  ),
  'gymnasium_alone_prefixed': (
    'import gymnasium',
    'robel_dm:robel_dm/DClawTurnFixed-v0',
  ),
  'gymnasium_then_robel_dm': (
    'import gymnasium\nimport robel_dm',
    'robel_dm/DClawTurnFixed-v0',
  ),
  'robel_dm_gym_prefixed': (
    'import robel_dm.learning.gym\nimport gymnasium',
    'robel_dm:robel_dm/DClawTurnFixed-v0',
  ),
  'robel_dm_gym': (
    'import robel_dm.learning.gym\nimport gymnasium',
    'robel_dm/DClawTurnFixed-v0',
  ),
  'gymnasium_then_robel_dm_gym': (
    'import gymnasium\nimport robel_dm.learning.gym',
    'robel_dm/DClawTurnFixed-v0',
  ),
  'robel_dm_train_then_make': (
    'import robel_dm.commands.train\nimport gymnasium',
    'robel_dm/DClawTurnFixed-v0',
  ),
}


def _run(code: str) -> subprocess.CompletedProcess:
  return subprocess.run(
    [sys.executable, '-c', textwrap.dedent(code)],
    capture_output=True,
    text=True,
    check=False,
  )


@pytest.mark.slow
@pytest.mark.parametrize(
  'imports, env_id', _IMPORT_ORDERS.values(), ids=_IMPORT_ORDERS
)
def test_every_documented_make_works_in_any_import_order(imports, env_id):
  result = _run(imports + _MAKE.format(env_id=env_id))
  assert result.returncode == 0, result.stderr


def test_importing_robel_dm_stays_light():
  result = _run("""
    import sys
    import robel_dm
    heavy = {'gymnasium', 'robel_dm.learning.gym', 'robel_dm.suite',
             'dm_control'}
    assert not heavy & set(sys.modules), heavy & set(sys.modules)
  """)
  assert result.returncode == 0, result.stderr


@pytest.mark.slow
def test_robel_dm_works_without_gymnasium():
  result = _run("""
    import sys
    sys.modules['gymnasium'] = None  # As if it were not installed.
    import robel_dm
    from robel_dm import suite
    env = suite.load('dclaw', 'pose_fixed', seed=0)
    env.reset()
    env.step([0.0] * 9)
    assert 'robel_dm.learning.gym' not in sys.modules
  """)
  assert result.returncode == 0, result.stderr


# --- Episode ends -------------------------------------------------------------


def test_step_before_the_first_reset_asks_for_a_reset():
  env = robel_gym.RobelEnv(*_TASK, seed=0)
  try:
    with pytest.raises(
      robel_gym.ResetNeededError, match=r'^call reset\(\) before step\(\)$'
    ) as info:
      env.step(np.zeros(_NUM_ACTIONS))
    # Gymnasium's error, as gymnasium.make's order check raises, and the
    # RuntimeError the adapter raised before.
    assert isinstance(info.value, gymnasium.error.ResetNeeded)
    assert isinstance(info.value, RuntimeError)
  finally:
    env.close()


@pytest.mark.parametrize('wrapped', [False, True], ids=['adapter', 'make'])
def test_step_after_the_episode_ended_asks_for_a_reset(wrapped, monkeypatch):
  if wrapped:  # With gymnasium.make's wrappers (order and passive checks).
    env = gymnasium.make('robel_dm/DClawPoseFixed-v0', time_limit=0.2)
  else:
    env = robel_gym.RobelEnv(*_TASK, time_limit=0.2)
  try:
    env.reset(seed=0)
    action = np.zeros(_NUM_ACTIONS, np.float32)
    steps, truncated = 0, False
    while not truncated:
      _, _, terminated, truncated, _ = env.step(action)
      assert not terminated
      steps += 1
    robel_env = env.unwrapped.robel_env
    assert steps == round(0.2 / robel_env.control_timestep())
    step = mock.Mock(wraps=robel_env.step)
    monkeypatch.setattr(robel_env, 'step', step)
    for _ in range(2):
      with pytest.raises(
        gymnasium.error.ResetNeeded,
        match=r'^the episode ended: call reset\(\) before step\(\)$',
      ) as info:
        env.step(action)
      assert isinstance(info.value, RuntimeError)  # As before the 1st reset.
    step.assert_not_called()
    env.reset(seed=0)
    _, reward, terminated, truncated, _ = env.step(action)
    assert isinstance(reward, float) and not (terminated or truncated)
  finally:
    env.close()
