"""Tests of `robel_dm.suite`: registry, dm_env conformance, episode timing."""

from absl.testing import absltest
import dm_env
from dm_env import test_utils
import numpy as np
import pytest

from robel_dm import constants, suite

# ROBEL's episode length (control steps) and control timestep (s) per task
# family (robel_facts section 1); the family is the task name's first word.
_ROBEL_TIMING = {'pose': (80, 0.05), 'turn': (40, 0.1), 'screw': (80, 0.1)}
_ROBEL_PHYSICS_TIMESTEP = 0.0025


def _family(task_id):
  family = task_id[1].split('_')[0]
  assert family in _ROBEL_TIMING, f'no ROBEL timing for {task_id}'
  return family


# --- dm_env conformance ------------------------------------------------------


class _ConformanceTest(test_utils.EnvironmentTestMixin, absltest.TestCase):
  """dm_env's interface checks, run on one registered task.

  The mixin's default action sequence (20 copies of the spec minimum) is too
  short to reach the end of an episode, so `make_action_sequence` runs past
  the time limit: the mixin then also checks that LAST is followed by FIRST.
  """

  TASK_ID = None  # Set by the generated subclasses.

  def make_object_under_test(self):
    return suite.load(*self.TASK_ID, seed=0)

  def make_action_sequence(self):
    spec = self.environment.action_spec()
    rng = np.random.default_rng(0)
    steps = self.environment.task.episode_steps + 3
    for i in range(steps):
      if i % 3 == 0:
        yield spec.generate_value()  # The spec minimum.
      elif i % 3 == 1:
        yield np.full(spec.shape, spec.maximum, spec.dtype)
      else:
        yield rng.uniform(spec.minimum, spec.maximum, spec.shape)

  def test_action_sequence_reaches_last_then_first(self):
    self.reset_environment()
    types = [
      self.step_environment(action).step_type
      for action in self.make_action_sequence()
    ]
    self.assertIn(dm_env.StepType.LAST, types)
    last = types.index(dm_env.StepType.LAST)
    self.assertIs(types[last + 1], dm_env.StepType.FIRST)


for _domain, _task in suite.ALL_TASKS:
  _name = f'TestConformance_{_domain}_{_task}'
  globals()[_name] = type(
    _name, (_ConformanceTest,), {'TASK_ID': (_domain, _task)}
  )
del _ConformanceTest  # Abstract: keep pytest from collecting it.


# --- Registry ----------------------------------------------------------------


def test_registry_lists_the_dclaw_tasks():
  assert suite.ALL_TASKS
  assert set(suite.TASKS_BY_DOMAIN) == {'dclaw'}
  assert suite.TASKS_BY_DOMAIN['dclaw'] == tuple(
    task for _, task in suite.ALL_TASKS
  )
  assert {_family(task_id) for task_id in suite.ALL_TASKS} == set(_ROBEL_TIMING)


def test_variant_tags_partition_the_registry():
  tagged = suite.FIXED + suite.RANDOM + suite.RANDOM_DYNAMICS
  assert sorted(tagged) == sorted(suite.ALL_TASKS)
  # Each family has exactly one task of each variant.
  for variant in (suite.FIXED, suite.RANDOM, suite.RANDOM_DYNAMICS):
    families = [_family(task_id) for task_id in variant]
    assert sorted(families) == sorted(_ROBEL_TIMING)


# --- Episode timing ----------------------------------------------------------


def _run_episode(env, rng):
  """Steps `env` (just reset) to the end of the episode; returns #steps."""
  steps = 0
  while True:
    timestep = env.step(rng.uniform(-1.0, 1.0, 9))
    steps += 1
    if timestep.last():
      return steps
    assert timestep.mid()
    assert steps < 1000, 'the episode never ends'


def test_episode_length_and_timesteps_are_robels(task_id):
  episode_steps, control_timestep = _ROBEL_TIMING[_family(task_id)]
  env = suite.load(*task_id, seed=0)
  assert env.control_timestep() == pytest.approx(control_timestep, abs=1e-12)
  assert env.physics.timestep() == _ROBEL_PHYSICS_TIMESTEP
  assert constants.PHYSICS_TIMESTEP == _ROBEL_PHYSICS_TIMESTEP
  assert env.task.physics_steps_per_control_step == round(
    control_timestep / _ROBEL_PHYSICS_TIMESTEP
  )
  assert env.task.episode_steps == episode_steps
  rng = np.random.default_rng(0)

  first = env.reset()
  assert first.first()
  assert _run_episode(env, rng) == episode_steps
  assert env.physics.data.time == pytest.approx(
    episode_steps * control_timestep
  )
  # After LAST the next step resets (and ignores its action) ...
  auto = env.step(np.full(9, np.nan))
  assert auto.first()
  assert auto.reward is None and auto.discount is None
  assert env.physics.data.time == 0.0
  # ... and the next episode has the same length.
  assert _run_episode(env, rng) == episode_steps


def test_time_limit_argument_overrides_the_episode_length():
  # composer ends the episode once physics time >= time_limit; 0.95 s is
  # reached at the 10th step of 0.1 s (away from float-rounding ties).
  env = suite.load('dclaw', 'turn_fixed', seed=0, time_limit=0.95)
  env.reset()
  assert _run_episode(env, np.random.default_rng(0)) == 10


def test_time_limit_of_whole_control_steps_gives_that_many_steps(task_id):
  # ROBEL's own episode length in seconds must give ROBEL's step count,
  # even though the accumulated physics time carries rounding error.
  episode_steps, control_timestep = _ROBEL_TIMING[_family(task_id)]
  seconds = episode_steps * control_timestep  # 4 s or 8 s.
  env = suite.load(*task_id, seed=0, time_limit=seconds)
  env.reset()
  assert _run_episode(env, np.random.default_rng(0)) == episode_steps


def test_discount_is_one_during_and_at_the_end_of_episodes():
  env = suite.load('dclaw', 'turn_fixed', seed=0)
  env.reset()
  while True:
    timestep = env.step(np.zeros(9))
    assert timestep.discount == 1.0  # Time-limit ends are not terminal.
    if timestep.last():
      break


# --- Bad arguments -----------------------------------------------------------


def test_unknown_domain_raises():
  with pytest.raises(ValueError, match="'dkitty_bogus'"):
    suite.load('dkitty_bogus', 'turn_fixed')


def test_unknown_task_raises_with_its_name_and_a_hint():
  with pytest.raises(ValueError, match="'turn_fxied'") as info:
    suite.load('dclaw', 'turn_fxied')
  assert 'turn_fixed' in str(info.value)


def test_unknown_task_keyword_raises_value_error():
  with pytest.raises(ValueError, match='bogus_keyword'):
    suite.load('dclaw', 'turn_fixed', task_kwargs={'bogus_keyword': 1})


def test_unknown_valve_raises_value_error():
  with pytest.raises(ValueError, match="'valve5'"):
    suite.load('dclaw', 'turn_fixed', task_kwargs={'valve': 'valve5'})


def test_unknown_observation_key_raises_value_error(task_id):
  with pytest.raises(ValueError, match='not_an_observation'):
    suite.load(
      *task_id, task_kwargs={'observation_keys': ('not_an_observation',)}
    )


def test_unknown_action_bounds_mode_raises_value_error():
  with pytest.raises(ValueError, match='action_bounds'):
    suite.load('dclaw', 'pose_fixed', task_kwargs={'action_bounds': 'wrap'})
