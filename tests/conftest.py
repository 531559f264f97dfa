"""Shared pytest configuration for the robel_dm tests.

Selects headless EGL rendering before anything imports dm_control, and
parameterizes tests over the task registry: a test that takes `task_id`
runs once per task of `suite.ALL_TASKS`; `fixed_task_id`, `random_task_id`,
`dynamics_task_id` and `nominal_task_id` select the Fixed, Random,
RandomDynamics and not-RandomDynamics variants of every domain. With a
domain prefix (`dclaw_task_id`, `dkitty_dynamics_task_id`, ...) they select
that domain's tasks only.
"""

import os

os.environ.setdefault('MUJOCO_GL', 'egl')

import pytest  # noqa: E402

from robel_dm import suite  # noqa: E402

_VARIANTS = {
  'task_id': suite.ALL_TASKS,
  'fixed_task_id': suite.FIXED,
  'random_task_id': suite.RANDOM,
  'dynamics_task_id': suite.RANDOM_DYNAMICS,
  'nominal_task_id': tuple(
    task for task in suite.ALL_TASKS if task not in suite.RANDOM_DYNAMICS
  ),
}
_TASK_PARAMETERS = dict(_VARIANTS)
for _domain in suite.TASKS_BY_DOMAIN:
  for _name, _tasks in _VARIANTS.items():
    _TASK_PARAMETERS[f'{_domain}_{_name}'] = tuple(
      task for task in _tasks if task[0] == _domain
    )


def pytest_generate_tests(metafunc):
  # A test marked `quick_on_first_task` runs its first task in the quick
  # tier (`-m "not slow"`) and the others in the full suite only.
  first_only = metafunc.definition.get_closest_marker('quick_on_first_task')
  for name, tasks in _TASK_PARAMETERS.items():
    if name in metafunc.fixturenames:
      assert tasks, f'no tasks for {name}'
      metafunc.parametrize(
        name,
        [
          pytest.param(task, marks=pytest.mark.slow if first_only and i else ())
          for i, task in enumerate(tasks)
        ],
        ids=[f'{domain}-{task}' for domain, task in tasks],
      )


@pytest.fixture(scope='session')
def shared_env():
  """Returns a function that loads (once per session) a task's environment.

  The environments are built with seed 0 and default arguments. Tests that
  use them must reset them first and must not change their model.
  """
  cache = {}

  def load(task_id):
    if task_id not in cache:
      cache[task_id] = suite.load(*task_id, seed=0)
    return cache[task_id]

  yield load
  for env in cache.values():
    env.close()


@pytest.fixture(scope='module')
def kitty_envs():
  """The D'Kitty Fixed tasks' environments, loaded once per module."""
  envs = {
    family: suite.load('dkitty', f'{family}_fixed', seed=0)
    for family in ('stand', 'orient', 'walk')
  }
  yield envs
  for env in envs.values():
    env.close()


# --- Commands and what they build --------------------------------------------


@pytest.fixture(scope='module')
def evaluate_flags():
  """The evaluate command's flags, defined for one test module only."""
  from absl import flags  # noqa: PLC0415

  from robel_dm.evaluation import cli  # noqa: PLC0415

  before = set(flags.FLAGS)
  cli.define_flags()
  yield
  flags.FLAGS.unparse_flags()
  for name in set(flags.FLAGS) - before:
    delattr(flags.FLAGS, name)


@pytest.fixture
def built(monkeypatch):
  """The environments `suite.load` builds during the test."""
  calls = []
  load = suite.load

  def watched(*args, **kwargs):
    calls.append((args, kwargs))
    return load(*args, **kwargs)

  monkeypatch.setattr(suite, 'load', watched)
  return calls


# --- ROBEL's rewards (docs/robel_reference.md sections 2.5-2.7) ---------------
