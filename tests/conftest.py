"""Shared pytest configuration for the robel_dm tests.

Selects headless EGL rendering before anything imports dm_control, and
parameterizes tests over the task registry: a test that takes `task_id`
runs once per task of `suite.ALL_TASKS`; `fixed_task_id`, `random_task_id`,
`dynamics_task_id` and `nominal_task_id` select the Fixed, Random,
RandomDynamics and not-RandomDynamics variants.
"""

import os

os.environ.setdefault('MUJOCO_GL', 'egl')

import pytest  # noqa: E402

from robel_dm import suite  # noqa: E402

_TASK_PARAMETERS = {
  'task_id': suite.ALL_TASKS,
  'fixed_task_id': suite.FIXED,
  'random_task_id': suite.RANDOM,
  'dynamics_task_id': suite.RANDOM_DYNAMICS,
  'nominal_task_id': tuple(
    task for task in suite.ALL_TASKS if task not in suite.RANDOM_DYNAMICS
  ),
}


def pytest_generate_tests(metafunc):
  for name, tasks in _TASK_PARAMETERS.items():
    if name in metafunc.fixturenames:
      metafunc.parametrize(
        name, tasks, ids=[f'{domain}-{task}' for domain, task in tasks]
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
