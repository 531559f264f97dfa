"""Tests every task must pass, whatever its robot.

ROBEL's definitions: docs/robel_reference.md sections 2.0 and 2.3.

Observation layout, signal types, the action map and its velocity clamp,
safety counters and the handling of bad actions, with expected values from
ROBEL's numbers in `robel_spec` (per domain), independently of robel_dm.
"""

import math

import numpy as np
import pytest
import robel_spec

from robel_dm import suite

_ONE_TASK_PER_DOMAIN = (('dclaw', 'pose_fixed'), ('dkitty', 'stand_fixed'))
_SIGNALS = ('score', 'success', 'safety')


def _signal(env, name):
  """The current value of a task observable (also disabled ones)."""
  return np.array(env.task.task_observables[name](env.physics))


def _joints(env):
  return env.physics.bind(env.task.robot.joints)


def _ctrl(env):
  return env.physics.bind(env.task.robot.actuators).ctrl.copy()


def _set_robot_state(env, qpos, qvel):
  """Writes the robot's joints and recomputes the task's signals."""
  _joints(env).qpos = qpos
  _joints(env).qvel = qvel
  env.physics.forward()
  env.task._update(env.physics, env.random_state)


def _action_map(task_id):
  """ROBEL's (center, half range) of every joint's action."""
  low, high = robel_spec.ACTION_RANGE[robel_spec.domain(task_id)]
  return (low + high) / 2, (high - low) / 2


# --- Observations ------------------------------------------------------------


@pytest.mark.slow
def test_agent_observation_is_robels_flat_layout(task_id, shared_env):
  family = robel_spec.family(task_id)
  layout = robel_spec.LAYOUTS[family]
  size = robel_spec.FLAT_SIZES[family]
  assert sum(n for _, n in layout) == size  # The test's own data.
  keys = tuple(key for key, _ in layout)
  env = shared_env(task_id)
  assert env.task.agent_observation_keys == keys
  timestep = env.reset()
  policy = robel_spec.steady_policy(env, seed=1)
  action = np.zeros(env.action_spec().shape)  # Zeros after reset.
  for _ in range(4):
    flat = env.task.flatten_observation(timestep.observation)
    assert flat.shape == (size,)
    assert flat.dtype == np.float64
    start = 0
    for key, entries in layout:
      value = np.ravel(timestep.observation[key])
      assert value.shape == (entries,), key
      np.testing.assert_array_equal(flat[start : start + entries], value)
      start += entries
    np.testing.assert_array_equal(timestep.observation['last_action'], action)
    action = policy(timestep)
    timestep = env.step(action)
    assert timestep.mid()
  # Agent keys come first in the observation dict, then the signals.
  assert tuple(timestep.observation) == keys + _SIGNALS


@pytest.mark.slow
@pytest.mark.parametrize(
  'task, keys',
  [
    (('dclaw', 'pose_fixed'), ('qvel', 'qpos')),
    (('dkitty', 'walk_fixed'), ('kitty_qvel', 'kitty_qpos')),
  ],
  ids=robel_spec.ids((('dclaw', 'pose_fixed'), ('dkitty', 'walk_fixed'))),
)
def test_custom_observation_keys_set_the_order(task, keys):
  env = suite.load(*task, seed=0, task_kwargs={'observation_keys': keys})
  assert env.task.agent_observation_keys == keys
  env.reset()
  obs = env.step(np.full(env.action_spec().shape, 0.3)).observation
  assert tuple(obs) == keys + _SIGNALS
  flat = env.task.flatten_observation(obs)
  joints = len(env.task.robot.joints)
  assert flat.shape == (2 * joints,)
  np.testing.assert_array_equal(flat[:joints], _joints(env).qvel)
  np.testing.assert_array_equal(flat[joints:], _joints(env).qpos)


@pytest.mark.slow
def test_every_feature_and_the_reward_terms_can_be_observed(task_id):
  features = tuple(suite.load(*task_id).task.FEATURES)
  env = suite.load(*task_id, seed=0,
                   task_kwargs={'observation_keys': features})  # fmt: skip
  env.task.task_observables['reward_terms'].enabled = True
  timestep = env.reset()
  spec = env.observation_spec()  # After the reset that applied the flag.
  assert tuple(spec) == features + _SIGNALS + ('reward_terms',)
  policy = robel_spec.steady_policy(env, seed=10)
  for _ in range(3):
    for key, value in timestep.observation.items():
      spec[key].validate(value)
    timestep = env.step(policy(timestep))
    assert timestep.mid()
    terms = timestep.observation['reward_terms']
    np.testing.assert_array_equal(terms, list(env.task.reward_terms.values()))
    assert terms.sum() == pytest.approx(timestep.reward, abs=1e-12)


@pytest.mark.slow
def test_signals_are_finite_and_typed_every_step(task_id, shared_env):
  env = shared_env(task_id)
  joints = env.action_spec().shape[0]
  timestep = env.reset()
  policy = robel_spec.steady_policy(env, seed=3)
  seen_last = False
  for step in range(env.task.episode_steps + 2):
    if step:
      timestep = env.step(policy(timestep))
    if timestep.first():
      assert timestep.reward is None
    else:
      assert type(timestep.reward) in (float, np.float64)
      assert math.isfinite(timestep.reward)
    seen_last |= timestep.last()
    obs = timestep.observation
    assert obs['score'].dtype == np.float64 and obs['score'].shape == ()
    assert np.isfinite(obs['score'])
    assert obs['success'].dtype == np.bool_ and obs['success'].shape == ()
    assert obs['safety'].dtype == np.int32 and obs['safety'].shape == (3,)
    assert np.all((obs['safety'] >= 0) & (obs['safety'] <= joints))
    assert obs['safety'][2] == 0  # No current is simulated.
    for key in env.task.agent_observation_keys:
      assert obs[key].dtype == np.float64
      assert np.all(np.isfinite(obs[key]))
    assert all(math.isfinite(v) for v in env.task.reward_terms.values())
  assert seen_last


# --- Actions -----------------------------------------------------------------


def test_action_ranges_are_robels(task_id, shared_env):
  env = shared_env(task_id)
  low, high = robel_spec.ACTION_RANGE[robel_spec.domain(task_id)]
  spec = env.action_spec()
  assert spec.shape == low.shape
  assert spec.dtype == np.float64
  np.testing.assert_array_equal(spec.minimum, -1.0)
  np.testing.assert_array_equal(spec.maximum, 1.0)
  ctrlrange = env.physics.bind(env.task.robot.actuators).ctrlrange
  np.testing.assert_allclose(ctrlrange[:, 0], low, rtol=0, atol=1e-12)
  np.testing.assert_allclose(ctrlrange[:, 1], high, rtol=0, atol=1e-12)


def test_normalize_joint_targets_inverts_the_action_map(task_id, shared_env):
  env = shared_env(task_id)
  center, half = _action_map(task_id)
  actions = np.random.default_rng(11).uniform(-1, 1, (5, center.size))
  for action in actions:
    targets = center + action * half
    np.testing.assert_allclose(
      env.task.normalize_joint_targets(targets), action, atol=1e-12
    )
  # Targets outside the range map to the bounds.
  low, high = center - half, center + half
  np.testing.assert_array_equal(env.task.normalize_joint_targets(low - 1), -1)
  np.testing.assert_array_equal(env.task.normalize_joint_targets(high + 1), 1)


def test_action_mapping_and_velocity_clamp(task_id, shared_env):
  env = shared_env(task_id)
  env.reset()
  domain = robel_spec.domain(task_id)
  center, half = _action_map(task_id)
  max_step = robel_spec.MAX_JOINT_SPEED[domain] * env.control_timestep()
  joints = center.size
  signs = np.resize([1, -1, 1, 1, 0, -1, 1, -1, 1], joints)
  qpos = center + 0.2 * half * np.resize([1, -1, 1], joints)
  # Violates the clamp: full range moves much further than one step allows.
  big = np.resize([1, 1, 1, -1, -1, -1, 1, -1, 0.5], joints)
  # Respects it: targets 0.4 steps away from the current position.
  target = qpos + 0.4 * max_step * signs
  small = (target - center) / half
  assert np.all(np.abs(small) <= 1)
  for action, clamped in ((big, True), (small, False)):
    _set_robot_state(env, qpos, np.zeros(joints))
    env.task.before_step(env.physics, action, env.random_state)
    mapped = center + action * half
    expected = np.clip(mapped, qpos - max_step, qpos + max_step)
    assert np.any(expected != mapped) == clamped
    np.testing.assert_allclose(_ctrl(env), expected, atol=1e-12)
  assert np.abs(_ctrl(env) - target).max() < 1e-12


def test_last_action_and_ctrl_after_real_steps(task_id, shared_env):
  env = shared_env(task_id)
  env.reset()
  rng = np.random.default_rng(7)
  domain = robel_spec.domain(task_id)
  center, half = _action_map(task_id)
  max_step = robel_spec.MAX_JOINT_SPEED[domain] * env.control_timestep()
  clamped = 0
  for _ in range(5):
    qpos = _joints(env).qpos.copy()
    action = rng.uniform(-1, 1, center.size)
    timestep = env.step(action)
    np.testing.assert_array_equal(timestep.observation['last_action'], action)
    mapped = center + action * half
    expected = np.clip(mapped, qpos - max_step, qpos + max_step)
    np.testing.assert_allclose(_ctrl(env), expected, atol=1e-12)
    clamped += np.count_nonzero(expected != mapped)
    if timestep.last():  # Random actions may topple the D'Kitty.
      break
  assert clamped > 0  # The clamp was exercised.


def _bad_actions(joints):
  zeros = np.zeros(joints)
  return {
    'nan': (np.r_[0.0, np.nan, zeros[2:]], 'non-finite'),
    'inf': (np.r_[zeros[1:], np.inf], 'non-finite'),
    '-inf': (np.r_[-np.inf, zeros[1:]], 'non-finite'),
    'short': (zeros[1:], 'shape'),
    'long': (np.zeros(joints + 1), 'shape'),
    'column': (np.zeros((joints, 1)), 'shape'),
    'scalar': (np.float64(0.0), 'shape'),
    'out_of_range': (np.r_[zeros[:4], 1.5, zeros[5:]], 'outside'),
  }


@pytest.mark.parametrize('kind', list(_bad_actions(9)))
@pytest.mark.parametrize(
  'task', _ONE_TASK_PER_DOMAIN, ids=robel_spec.ids(_ONE_TASK_PER_DOMAIN)
)
def test_bad_actions_raise_and_leave_ctrl_alone(task, kind, shared_env):
  env = shared_env(task)
  timestep = env.reset()
  policy = robel_spec.steady_policy(env)
  joints = env.action_spec().shape[0]
  timestep = env.step(policy(timestep))
  before = _ctrl(env)
  action, message = _bad_actions(joints)[kind]
  with pytest.raises(ValueError, match=message):
    env.step(action)
  np.testing.assert_array_equal(_ctrl(env), before)
  assert np.all(np.isfinite(env.physics.data.ctrl))
  # The environment carries on normally.
  action = policy(timestep)
  timestep = env.step(action)
  assert timestep.mid()
  np.testing.assert_array_equal(timestep.observation['last_action'], action)


@pytest.mark.slow
def test_actions_of_the_other_robot_are_rejected():
  for task, joints in ((('dclaw', 'turn_fixed'), 12),
                       (('dkitty', 'walk_fixed'), 9)):  # fmt: skip
    env = suite.load(*task, seed=0)
    env.reset()
    with pytest.raises(ValueError, match='shape'):
      env.step(np.zeros(joints))


@pytest.mark.parametrize(
  'task', _ONE_TASK_PER_DOMAIN, ids=robel_spec.ids(_ONE_TASK_PER_DOMAIN)
)
def test_clip_mode_clips_out_of_range_actions_but_not_nan(task):
  env = suite.load(*task, seed=0, task_kwargs={'action_bounds': 'clip'})
  env.reset()
  center, half = _action_map(task)
  joints = center.size
  action = np.resize([1.5, -3.0, 0.2, 1.0, -1.0, 7.0, 0.0, -1.01, 0.5], joints)
  clipped = np.clip(action, -1, 1)
  qpos = _joints(env).qpos.copy()
  timestep = env.step(action)
  np.testing.assert_array_equal(timestep.observation['last_action'], clipped)
  domain = robel_spec.domain(task)
  max_step = robel_spec.MAX_JOINT_SPEED[domain] * env.control_timestep()
  mapped = center + clipped * half
  expected = np.clip(mapped, qpos - max_step, qpos + max_step)
  np.testing.assert_allclose(_ctrl(env), expected, atol=1e-12)
  before = _ctrl(env)
  with pytest.raises(ValueError, match='non-finite'):
    env.step(np.r_[np.nan, np.zeros(joints - 1)])
  np.testing.assert_array_equal(_ctrl(env), before)


@pytest.mark.slow
@pytest.mark.parametrize(
  'task', _ONE_TASK_PER_DOMAIN, ids=robel_spec.ids(_ONE_TASK_PER_DOMAIN)
)
def test_rounding_excess_is_clipped_even_when_raising(task):
  env = suite.load(*task, seed=0)
  env.reset()
  joints = env.action_spec().shape[0]
  action = np.r_[1 + 1e-9, -1 - 1e-9, np.zeros(joints - 2)]
  timestep = env.step(action)
  np.testing.assert_array_equal(
    timestep.observation['last_action'], np.r_[1.0, -1.0, np.zeros(joints - 2)]
  )


# --- Safety ------------------------------------------------------------------

# Hand-built joint states: position and velocity violations per domain.
_SAFETY_STATES = {
  'dclaw': (
    np.array([0.43, -1.04, 1.47, -0.58, 0.0, 0.0, 0.0, 1.0, -1.5]),
    np.array([1.5, -1.2, 0.9, -0.99, 0.0, 3.0, 0.0, 0.0, -1.01]),
    (5, 4),
  ),
  # Legs FR, FL, BL, BR (hip, upper leg, knee). Within 5 degrees of a joint
  # limit: the FR and FL hips, FL upper leg and knee, BR knee. Within 5
  # degrees of (or beyond) the action range, which does not count: also the
  # FR, BL and BR upper legs and the BR hip (8 in all, FL knee excluded).
  'dkitty': (
    np.array([0.25, 0.0, -1.0, -0.2, 2.1, -1.52,
              0.0, np.pi / 2, -0.5, -0.45, -2.0, 1.5]),
    np.array([3.2, -3.15, 3.1, -3.0, 0.0, 5.0,
              0.0, -np.pi + 1e-3, 0.0, 0.0, -4.0, 1.0]),
    (5, 4),
  ),
}  # fmt: skip


def _near_limits(qpos, low, high):
  return np.minimum(qpos - low, high - qpos) < robel_spec.SAFETY_MARGIN


def test_safety_counters_on_hand_built_states(task_id, shared_env):
  env = shared_env(task_id)
  env.reset()
  domain = robel_spec.domain(task_id)
  low, high = robel_spec.SAFETY_RANGE[domain]
  speed = robel_spec.SAFETY_SPEED[domain]
  qpos, qvel, counts = _SAFETY_STATES[domain]
  near_limit = _near_limits(qpos, low, high)
  too_fast = np.abs(qvel) > speed
  assert (near_limit.sum(), too_fast.sum()) == counts  # The test's own data.
  if domain == 'dkitty':
    # The position counter watches the joint range, not the action range.
    action_low, action_high = robel_spec.ACTION_RANGE[domain]
    assert _near_limits(qpos, action_low, action_high).sum() == 8
  valve = None
  if robel_spec.family(task_id) in ('turn', 'screw'):
    valve = env.physics.bind(env.task.valve.hinge)
    valve.qpos, valve.qvel = 0.0, 5.0  # The valve's speed does not count.
  joints = len(qpos)
  _set_robot_state(env, qpos, qvel)
  np.testing.assert_array_equal(_signal(env, 'safety'), [*counts, 0])
  _set_robot_state(env, (low + high) / 2, np.zeros(joints))
  np.testing.assert_array_equal(_signal(env, 'safety'), [0, 0, 0])
  _set_robot_state(env, high, -(speed + 1) * np.ones(joints))
  np.testing.assert_array_equal(_signal(env, 'safety'), [joints, joints, 0])
  _set_robot_state(env, low - 0.01, (speed + 0.01) * np.ones(joints))
  np.testing.assert_array_equal(_signal(env, 'safety'), [joints, joints, 0])
  if valve is not None:
    assert valve.qvel[0] == 5.0


_BAD_OPTIONS = (
  ('dclaw', 'turn_fixed', {'observation_noise': '0.1'}, 'observation_noise'),
  ('dclaw', 'turn_fixed', {'observation_noise': True}, 'observation_noise'),
  ('dclaw', 'turn_fixed', {'observation_noise': float('nan')}, 'finite'),
  ('dclaw', 'turn_fixed', {'observation_keys': 5}, 'observation_keys'),
  ('dclaw', 'turn_fixed', {'observation_keys': []}, 'observation_keys is'),
  ('dclaw', 'turn_fixed', {'dynamics': 'robel'}, 'dynamics must be'),
  ('dclaw', 'turn_fixed', {'success_threshold': -1.0}, 'success_threshold'),
  ('dclaw', 'turn_fixed', {'success_threshold': 'x'}, 'success_threshold'),
  ('dclaw', 'turn_fixed', {'episode_steps': 10.5}, 'episode_steps'),
  ('dclaw', 'turn_fixed', {'episode_steps': True}, 'episode_steps'),
  ('dclaw', 'turn_fixed', {'reward': {'bonus_big': 'x'}}, 'reward.bonus_big'),
  ('dclaw', 'turn_random_dynamics', {'privileged': 1}, 'privileged'),
  ('dkitty', 'walk_fixed', {'terrain': 'False'}, 'terrain must be'),
  ('dkitty', 'stand_fixed', {'settle_substeps': 10.5}, 'settle_substeps'),
  ('dclaw', 'pose_fixed', {'initial_pose': [10.0] * 9}, 'initial_pose: joint'),
  ('dclaw', 'pose_fixed', {'goal_pose': [0.1] * 3}, 'goal_pose needs 9'),
  ('dkitty', 'stand_fixed', {'initial_pose': [5.0] * 12}, 'initial_pose:'),
)


@pytest.mark.parametrize(('domain', 'task', 'options', 'message'), _BAD_OPTIONS)
def test_a_task_option_of_the_wrong_kind_is_one_line_naming_it(
  domain, task, options, message
):
  # Refused when the task is built, before an episode: not clipped,
  # defaulted or read as something else.
  with pytest.raises(ValueError, match=message):
    suite.load(domain, task, task_kwargs=options).reset()


def test_reward_constants_given_whole_are_checked_too():
  from robel_dm.tasks import dclaw_turn  # noqa: PLC0415

  reward = dclaw_turn.TurnReward(target_dist_weight=float('nan'))
  with pytest.raises(ValueError, match='reward.target_dist_weight'):
    suite.load('dclaw', 'turn_fixed', task_kwargs={'reward': reward})


def test_negative_randomized_physics_is_refused():
  from robel_dm import randomization  # noqa: PLC0415

  with pytest.raises(ValueError, match='dynamics.damping must not go below'):
    randomization.DynamicsRanges(damping=randomization.Range(-1.0, -0.5))
  with pytest.raises(ValueError, match='finite ends'):
    randomization.Range(0.0, float('inf'))


def test_task_kwargs_must_be_a_mapping():
  with pytest.raises(ValueError, match='task_kwargs must be a mapping'):
    suite.load('dclaw', 'turn_fixed', task_kwargs=[('valve', 'valve4')])
