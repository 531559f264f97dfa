"""The safe action map (`task_kwargs={'action_map': 'safe'}`): targets inside
the safety counters' bounds, moved no faster than their speed limit.

Expected values from the counters' definitions in `robel_spec`, not from
robel_dm.
"""

import numpy as np
import pytest
import robel_spec

from robel_dm import evaluation, policies, suite

# The map's margins (its documented constants): targets 1 degree inside the
# position counter's bounds, at 0.9 of its speed limit.
_BUFFER = np.deg2rad(1.0)
_SPEED_FRACTION = 0.9


def _safe_targets(domain):
  """The (low, high) targets of the safe map, from ROBEL's ranges."""
  action_low, action_high = robel_spec.ACTION_RANGE[domain]
  watched_low, watched_high = robel_spec.SAFETY_RANGE[domain]
  margin = robel_spec.SAFETY_MARGIN + _BUFFER
  return (
    np.maximum(action_low, watched_low + margin),
    np.minimum(action_high, watched_high - margin),
  )


def _safe_env(task_id):
  return suite.load(*task_id, task_kwargs={'action_map': 'safe'}, seed=0)


@pytest.mark.quick_on_first_task
def test_safe_map_keeps_targets_inside_the_counters_bounds(task_id):
  domain = robel_spec.domain(task_id)
  low, high = _safe_targets(domain)
  env = _safe_env(task_id)
  env.reset()
  max_step = (
    _SPEED_FRACTION
    * min(robel_spec.SAFETY_SPEED[domain], robel_spec.MAX_JOINT_SPEED[domain])
    * env.control_timestep()
  )
  joints = env.physics.bind(env.task.robot.joints)
  actuators = env.physics.bind(env.task.robot.actuators)
  for action in (np.ones(low.size), -np.ones(low.size)):
    # From the middle of the targets, the extremes are many steps away:
    # the clamp holds every step, and the targets end at the bounds.
    joints.qpos = (low + high) / 2
    joints.qvel = 0.0
    env.physics.forward()
    for _ in range(200):
      qpos = joints.qpos.copy()
      env.task.before_step(env.physics, action, env.random_state)
      ctrl = actuators.ctrl.copy()
      assert np.all(np.abs(ctrl - qpos) <= max_step + 1e-12)
      assert np.all(ctrl >= low - 1e-12) and np.all(ctrl <= high + 1e-12)
      joints.qpos = ctrl  # As if the joint had reached its target.
      env.physics.forward()
    np.testing.assert_allclose(ctrl, high if action[0] > 0 else low)
  env.close()


@pytest.mark.quick_on_first_task
def test_safe_map_inverse_and_robels_ranges(task_id):
  """`normalize_joint_targets` inverts the safe map; the ranges that
  observation noise and random poses use stay ROBEL's."""
  domain = robel_spec.domain(task_id)
  low, high = _safe_targets(domain)
  env = _safe_env(task_id)
  action = np.random.default_rng(3).uniform(-1, 1, low.size)
  targets = (low + high) / 2 + action * (high - low) / 2
  np.testing.assert_allclose(
    env.task.normalize_joint_targets(targets), action, atol=1e-12
  )
  action_map = env.task._action_map
  robel_low, robel_high = robel_spec.ACTION_RANGE[domain]
  np.testing.assert_allclose(action_map.low, robel_low)
  np.testing.assert_allclose(action_map.high, robel_high)
  env.close()


def test_safe_map_saturated_actions_count_no_violations():
  """A policy that slams every joint to its limits, the worst case of
  ROBEL's map, counts no position or velocity violation on the safe map
  (D'Claw Pose: ROBEL's map counts hundreds)."""

  def violations(action_map):
    env = suite.load(
      'dclaw', 'pose_fixed', task_kwargs={'action_map': action_map}, seed=0
    )
    timestep = env.reset()
    total = np.zeros(3)
    for step in range(80):
      sign = 1.0 if (step // 10) % 2 == 0 else -1.0
      timestep = env.step(np.full(9, sign))
      total += timestep.observation['safety']
    env.close()
    return total

  assert violations('robel')[:2].sum() > 100
  np.testing.assert_array_equal(violations('safe'), 0)


def test_unknown_action_map_raises_value_error():
  with pytest.raises(ValueError, match="action_map must be one of .*'wide'"):
    suite.load('dclaw', 'pose_fixed', task_kwargs={'action_map': 'wide'})


def _slamming_policy(tmp_path, action_map):
  """A Pose policy that drives every joint to +1 whatever it sees, saved
  as trained through `action_map`."""
  policy = policies.NumpyPolicy(
    [np.zeros((9, 27))],
    [np.full(9, 10.0)],
    'relu',
    'tanh',
    {
      'domain': 'dclaw',
      'task': 'pose_fixed',
      'task_kwargs': {'action_map': action_map},
      'observation_keys': ['qpos', 'last_action', 'qpos_error'],
      'algo': 'sac',
      'seed': 0,
    },
  )
  path = tmp_path / f'{action_map}.npz'
  policy.save(path)
  return path


def test_a_policy_is_evaluated_through_the_map_it_learned_with(tmp_path):
  lines = []

  def evaluate(path, task_kwargs=None):
    return evaluation.evaluate(
      evaluation.EvalConfig(
        'dclaw', 'pose_fixed', 1, policy=str(path), task_kwargs=task_kwargs,
        log=lines.append,
      )
    )  # fmt: skip

  safe = evaluate(_slamming_policy(tmp_path, 'safe'))
  assert safe['task_kwargs'] == {'action_map': 'safe'}
  assert lines == [
    'the policy learned with task option action_map=safe: evaluating with it'
  ]
  assert sum(safe['safety'].values()) == 0
  robel = evaluate(_slamming_policy(tmp_path, 'robel'))
  assert sum(robel['safety'].values()) > 0
  assert len(lines) == 1  # ROBEL's map is the default: nothing to say.
  with pytest.raises(
    policies.PolicyError, match='trained with action_map safe, not robel'
  ):
    evaluate(_slamming_policy(tmp_path, 'safe'), {'action_map': 'robel'})


def test_a_loaded_policy_of_another_variant_keeps_its_map(tmp_path):
  # What `evaluate --allow_other_variant` and the zoo pass: a policy
  # object, here a Pose Fixed one on Pose Random.
  policy = policies.load(_slamming_policy(tmp_path, 'safe'), any_variant=True)
  results = evaluation.evaluate(
    evaluation.EvalConfig('dclaw', 'pose_random', 1, policy=policy, seed=0)
  )
  assert results['task_kwargs'] == {'action_map': 'safe'}
  assert sum(results['safety'].values()) == 0
