"""Tests of `robel_dm.suite`: registry, dm_env conformance, episode timing."""

from absl.testing import absltest
import dm_env
from dm_env import test_utils
import numpy as np
import pytest
import robel_spec

from robel_dm import constants, suite
from robel_dm.entities import dkitty

# ROBEL's episode length (control steps) and control timestep (s) per task
# family (docs/robel_reference.md section 1); the family is the task name's
# first word.
_ROBEL_TIMING = robel_spec.TIMING
_ROBEL_PHYSICS_TIMESTEP = robel_spec.PHYSICS_TIMESTEP
_ONE_TASK_PER_DOMAIN = (('dclaw', 'turn_fixed'), ('dkitty', 'walk_fixed'))


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


# The quick tier (`-m "not slow"`) checks one task of each domain.
_QUICK_CONFORMANCE = {('dclaw', 'pose_fixed'), ('dkitty', 'orient_fixed')}
for _domain, _task in suite.ALL_TASKS:
  _name = f'TestConformance_{_domain}_{_task}'
  _class = type(_name, (_ConformanceTest,), {'TASK_ID': (_domain, _task)})
  if (_domain, _task) not in _QUICK_CONFORMANCE:
    _class = pytest.mark.slow(_class)
  globals()[_name] = _class
del _ConformanceTest  # Abstract: keep pytest from collecting it.


# --- Registry ----------------------------------------------------------------


def test_registry_lists_the_tasks_of_both_domains():
  assert len(suite.ALL_TASKS) == 18
  assert set(suite.TASKS_BY_DOMAIN) == {'dclaw', 'dkitty'}
  assert (
    tuple(
      (domain, task)
      for domain, tasks in suite.TASKS_BY_DOMAIN.items()
      for task in tasks
    )
    == suite.ALL_TASKS
  )
  for domain, families in robel_spec.FAMILIES.items():
    tasks = suite.TASKS_BY_DOMAIN[domain]
    assert len(tasks) == 9
    assert {_family((domain, task)) for task in tasks} == set(families)
  assert {_family(task_id) for task_id in suite.ALL_TASKS} == set(_ROBEL_TIMING)


def test_variant_tags_partition_the_registry():
  tagged = suite.FIXED + suite.RANDOM + suite.RANDOM_DYNAMICS
  assert sorted(tagged) == sorted(suite.ALL_TASKS)
  # Each family has exactly one task of each variant, named after it.
  suffixes = {'_fixed': suite.FIXED, '_random': suite.RANDOM,
              '_random_dynamics': suite.RANDOM_DYNAMICS}  # fmt: skip
  for suffix, variant in suffixes.items():
    families = [_family(task_id) for task_id in variant]
    assert sorted(families) == sorted(_ROBEL_TIMING)
    for domain, task in variant:
      assert task == _family((domain, task)) + suffix
      assert task in suite.TASKS_BY_DOMAIN[domain]


# --- Episode timing ----------------------------------------------------------


def _run_episode(env, policy, timestep):
  """Steps `env` from `timestep`, its episode's FIRST, to the episode's end.

  Returns:
    The number of steps and the LAST timestep.
  """
  assert timestep.first()
  steps = 0
  while True:
    timestep = env.step(policy(timestep))
    steps += 1
    if timestep.last():
      return steps, timestep
    assert timestep.mid()
    assert steps < 1000, 'the episode never ends'


def _run_to_the_time_limit(env, policy, timestep, attempts=10):
  """Runs episodes from `timestep` (a FIRST) until one reaches the time limit.

  Only a fall of the D'Kitty may end an episode before its time limit: LAST
  with discount 0. After such an episode, the next step (with a NaN action,
  which a reset ignores) must start a new one.

  Returns:
    The number of steps of the episode that reached the time limit.
  """
  episode_steps = env.task.episode_steps
  for _ in range(attempts):
    steps, last = _run_episode(env, policy, timestep)
    if last.discount == 1.0:
      return steps
    assert last.discount == 0.0
    assert steps < episode_steps
    assert isinstance(env.task.robot, dkitty.DKitty), "only the D'Kitty falls"
    timestep = env.step(np.full(env.action_spec().shape, np.nan))
    assert timestep.first()
    assert env.physics.data.time == 0.0
  pytest.fail(f'{attempts} episodes in a row ended in a fall')


@pytest.mark.slow
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
  assert env.task.time_limit == pytest.approx(episode_steps * control_timestep)
  policy = robel_spec.steady_policy(env)

  first = env.reset()
  assert first.first()
  assert env.physics.data.time == 0.0
  assert _run_to_the_time_limit(env, policy, first) == episode_steps
  assert env.physics.data.time == pytest.approx(
    episode_steps * control_timestep
  )
  # After LAST the next step resets (and ignores its action) ...
  auto = env.step(np.full(env.action_spec().shape, np.nan))
  assert auto.first()
  assert auto.reward is None and auto.discount is None
  assert env.physics.data.time == 0.0
  # ... and the next episode has the same length.
  assert _run_to_the_time_limit(env, policy, auto) == episode_steps


@pytest.mark.parametrize(
  'task', _ONE_TASK_PER_DOMAIN, ids=robel_spec.ids(_ONE_TASK_PER_DOMAIN)
)
def test_time_limit_argument_overrides_the_episode_length(task):
  # composer ends the episode once physics time >= time_limit; 0.95 s is
  # reached at the 10th step of 0.1 s (away from float-rounding ties).
  env = suite.load(*task, seed=0, time_limit=0.95)
  first = env.reset()
  policy = robel_spec.steady_policy(env)
  assert _run_to_the_time_limit(env, policy, first) == 10


@pytest.mark.slow
def test_time_limit_of_whole_control_steps_gives_that_many_steps(task_id):
  # ROBEL's own episode length in seconds must give ROBEL's step count,
  # even though the accumulated physics time carries rounding error.
  episode_steps, control_timestep = _ROBEL_TIMING[_family(task_id)]
  seconds = episode_steps * control_timestep  # 4 s, 8 s or 16 s.
  env = suite.load(*task_id, seed=0, time_limit=seconds)
  first = env.reset()
  policy = robel_spec.steady_policy(env, seed=1)
  assert _run_to_the_time_limit(env, policy, first) == episode_steps


@pytest.mark.slow
def test_discount_is_one_during_and_at_the_end_of_episodes(fixed_task_id):
  # The fixed tasks' steady policy never makes the D'Kitty fall.
  env = suite.load(*fixed_task_id, seed=0)
  timestep = env.reset()
  policy = robel_spec.steady_policy(env)
  steps = 0
  while True:
    timestep = env.step(policy(timestep))
    steps += 1
    assert timestep.discount == 1.0  # Time-limit ends are not terminal.
    if timestep.last():
      break
  assert steps == env.task.episode_steps


# --- Bad arguments -----------------------------------------------------------


def test_unknown_domain_raises():
  with pytest.raises(ValueError, match="'dkitty_bogus'"):
    suite.load('dkitty_bogus', 'turn_fixed')


@pytest.mark.parametrize(
  'domain, typo, task',
  [('dclaw', 'turn_fxied', 'turn_fixed'), ('dkitty', 'walk_fxied',
                                            'walk_fixed')],
)  # fmt: skip
def test_unknown_task_raises_with_its_name_and_a_hint(domain, typo, task):
  with pytest.raises(ValueError, match=f"'{typo}'") as info:
    suite.load(domain, typo)
  assert str(info.value).endswith(f'Did you mean {task!r}?')


def test_a_task_of_the_other_domain_is_named_as_such():
  with pytest.raises(
    ValueError, match="unknown dkitty task 'turn_fixed': that task belongs to"
  ):
    suite.load('dkitty', 'turn_fixed')
  with pytest.raises(ValueError, match='belongs to dkitty') as info:
    suite.load('dclaw', 'walk_fixed')
  assert 'screw' not in str(info.value)  # No misleading suggestion.


@pytest.mark.slow
@pytest.mark.parametrize(
  'task', _ONE_TASK_PER_DOMAIN, ids=robel_spec.ids(_ONE_TASK_PER_DOMAIN)
)
def test_unknown_task_keyword_raises_value_error(task):
  with pytest.raises(ValueError, match='bogus_keyword'):
    suite.load(*task, task_kwargs={'bogus_keyword': 1})


@pytest.mark.slow
def test_unknown_valve_raises_value_error():
  with pytest.raises(ValueError, match="'valve5'"):
    suite.load('dclaw', 'turn_fixed', task_kwargs={'valve': 'valve5'})
  # The D'Kitty's tasks have no valve.
  with pytest.raises(ValueError, match='valve'):
    suite.load('dkitty', 'walk_fixed', task_kwargs={'valve': 'valve3'})


@pytest.mark.slow
def test_unknown_observation_key_raises_value_error(task_id):
  with pytest.raises(ValueError, match='not_an_observation'):
    suite.load(
      *task_id, task_kwargs={'observation_keys': ('not_an_observation',)}
    )


@pytest.mark.parametrize(
  'task', _ONE_TASK_PER_DOMAIN, ids=robel_spec.ids(_ONE_TASK_PER_DOMAIN)
)
def test_unknown_action_bounds_mode_raises_value_error(task):
  with pytest.raises(ValueError, match='action_bounds'):
    suite.load(*task, task_kwargs={'action_bounds': 'wrap'})


@pytest.mark.slow
def test_positional_arguments_follow_dm_control_suite():
  env = suite.load(
    'dclaw',
    'turn_fixed',
    {'valve': 'valve4'},
    {'strip_singleton_obs_buffer_dim': False},  # Not the default.
  )
  timestep = env.reset()
  assert env.task.valve.variant == 'valve4'
  assert timestep.observation['claw_qpos'].shape == (1, 9)
  env.close()
  with pytest.raises(TypeError):
    suite.load('dclaw')


@pytest.mark.parametrize(
  'keyword',
  [
    {'device_path': 'virtual'},
    {'robot_config': 'claw.json'},
    {'reset': 'move'},
    {'tracker': 'natnet:127.0.0.1,rigid_body=1'},
    {'guide': 'show'},
    {'domain_name': 'dclaw'},
    {'task_name': 'pose_fixed'},
    {'visualize_reward': True},
  ],
  ids=lambda keyword: next(iter(keyword)),
)
def test_the_robot_comes_only_through_robot_options(keyword):
  with pytest.raises(TypeError, match='unexpected keyword argument'):
    suite.load('dclaw', 'pose_fixed', **keyword)


def test_robot_must_be_robot_options():
  with pytest.raises(ValueError, match='robot must be a suite.RobotOptions'):
    suite.load('dclaw', 'pose_fixed', robot='virtual')


def test_dm_control_habits_are_met():
  assert suite.BENCHMARKING == suite.ALL_TASKS and len(suite.BENCHMARKING) == 18
  with pytest.raises(ValueError, match='pass seed= to suite.load'):
    suite.load('dclaw', 'pose_fixed', task_kwargs={'random': 0})
