"""Tests of the D'Claw tasks against ROBEL's definitions.

Expected values are computed here, independently of robel_dm, from the
formulas and constants of docs/robel_reference.md (sections 2.0-2.3): reward
terms, scores, success criteria, initial states and goals, and the valves.
What every task shares (observation layout, action map, safety counters) is in
test_tasks.py.
"""

import math

import numpy as np
import pytest

from robel_dm import suite

# --- ROBEL's constants (docs/robel_reference.md sections 2.0-2.3) -------------

# Action ranges per joint (top, middle, bottom) x 3 fingers, rad.
_HALF_RANGE = np.tile([0.48, np.pi / 3, np.pi / 2], 3)
_LOW, _HIGH = -_HALF_RANGE, _HALF_RANGE
_RESET_POSE = np.tile([0.0, -np.pi / 3, np.pi / 3], 3)
_POSE_TERMS = ('pose_error_cost', 'joint_vel_cost')
_VALVE_TERMS = ('target_dist_cost', 'pose_diff_cost', 'joint_vel_cost',
                'bonus_small', 'bonus_big')  # fmt: skip


def _family(task_id):
  return task_id[1].split('_')[0]


def _is_pose(task_id):
  return _family(task_id) == 'pose'


_DCLAW_TASKS = suite.TASKS_BY_DOMAIN['dclaw']
_VALVE_TASKS = tuple(
  ('dclaw', task) for task in _DCLAW_TASKS if not _is_pose(('dclaw', task))
)
_VALVE_RANDOM_TASKS = tuple(
  t for t in suite.RANDOM + suite.RANDOM_DYNAMICS if t in _VALVE_TASKS
)


def _ids(tasks):
  return [f'{domain}-{task}' for domain, task in tasks]


def _wrap(angle):
  """Wraps to (-pi, pi] via the complex plane (independent of robel_dm)."""
  return float(np.angle(np.exp(1j * angle)))


def _pose_expected(goal, qpos, qvel):
  """ROBEL's Pose reward terms and points.

  ROBEL's definition: docs/robel_reference.md section 2.1.
  """
  error = goal - qpos
  fast = np.abs(qvel) >= np.pi
  terms = {
    'pose_error_cost': -np.linalg.norm(error),
    'joint_vel_cost': -0.1 * np.linalg.norm(qvel[fast]),
  }
  points = 1 - min(np.mean(np.abs(error)) / (np.pi / 4), 1)
  return terms, points


def _valve_expected(goal, claw_qpos, claw_qvel, valve_angle):
  """ROBEL's Turn/Screw reward terms and points.

  ROBEL's definition: docs/robel_reference.md section 2.2.
  """
  distance = abs(_wrap(goal - valve_angle))
  fast = np.abs(claw_qvel) >= 0.5
  terms = {
    'target_dist_cost': -5 * distance,
    'pose_diff_cost': -np.linalg.norm(claw_qpos - _RESET_POSE),
    'joint_vel_cost': -np.linalg.norm(claw_qvel[fast]),
    'bonus_small': 10.0 * (distance < 0.25),
    'bonus_big': 50.0 * (distance < 0.1),
  }
  return terms, 1 - distance / np.pi


def _signal(env, name):
  """The current value of a task observable (also disabled ones)."""
  return np.array(env.task.task_observables[name](env.physics))


def _claw(env):
  return env.physics.bind(env.task.robot.joints)


def _valve(env):
  return env.physics.bind(env.task.valve.hinge)


def _set_state(env, qpos, qvel, valve_qpos=None, valve_qvel=0.0):
  """Writes a hand-built state and recomputes the task's signals from it."""
  _claw(env).qpos = qpos
  _claw(env).qvel = qvel
  if valve_qpos is not None:
    _valve(env).qpos = valve_qpos
    _valve(env).qvel = valve_qvel
  env.task._update(env.physics, env.random_state)


def _expected_terms(env, task_id):
  """Reward terms and points of the current (true) physics state."""
  claw = _claw(env)
  if _is_pose(task_id):
    return _pose_expected(env.task.goal, claw.qpos.copy(), claw.qvel.copy())
  return _valve_expected(
    env.task.goal,
    claw.qpos.copy(),
    claw.qvel.copy(),
    float(_valve(env).qpos[0]),
  )


# --- Observations ------------------------------------------------------------


def test_noise_free_observations_match_the_true_state(
  dclaw_nominal_task_id, shared_env
):
  task_id = dclaw_nominal_task_id
  env = shared_env(task_id)
  assert env.task.observation_noise == 0  # Noisy ones: test_randomization.
  env.reset()
  timestep = env.step(np.random.default_rng(2).uniform(-1, 1, 9))
  obs = timestep.observation
  claw_qpos = _claw(env).qpos
  if _is_pose(task_id):
    np.testing.assert_array_equal(obs['qpos'], claw_qpos)
    np.testing.assert_allclose(
      obs['qpos_error'], env.task.goal - claw_qpos, atol=1e-12
    )
  else:
    angle = float(_valve(env).qpos[0])
    np.testing.assert_array_equal(obs['claw_qpos'], claw_qpos)
    np.testing.assert_allclose(obs['object_x'], [math.cos(angle)])
    np.testing.assert_allclose(obs['object_y'], [math.sin(angle)])
    error = float(obs['target_error'][0])
    assert -np.pi <= error < np.pi
    assert _wrap(error - (env.task.goal - angle)) == pytest.approx(0, abs=1e-9)


# --- Rewards, scores, success ------------------------------------------------


def test_reward_is_the_sum_of_robels_terms_on_real_steps(
  dclaw_task_id, shared_env
):
  task_id = dclaw_task_id
  env = shared_env(task_id)
  rng = np.random.default_rng(4)
  env.reset()
  names = _POSE_TERMS if _is_pose(task_id) else _VALVE_TERMS
  for _ in range(12):
    timestep = env.step(rng.uniform(-1, 1, 9))
    expected, points = _expected_terms(env, task_id)
    terms = env.task.reward_terms
    assert tuple(terms) == names
    for name in names:
      assert terms[name] == pytest.approx(expected[name], abs=1e-9), name
    assert timestep.reward == pytest.approx(sum(expected.values()), abs=1e-9)
    assert timestep.reward == pytest.approx(sum(terms.values()), abs=1e-12)
    assert timestep.observation['score'] == pytest.approx(points, abs=1e-9)


@pytest.mark.slow
def test_pose_terms_on_hand_built_states():
  env = suite.load('dclaw', 'pose_fixed', seed=0)
  env.reset()
  goal = env.task.goal
  rng = np.random.default_rng(5)
  velocities = [
    np.zeros(9),
    np.array([3.2, -3.5, 0.1, np.pi, -np.pi, 3.0, -3.1, 0.0, 10.0]),
    rng.uniform(-6, 6, 9),
  ]
  for qvel in velocities:
    qpos = rng.uniform(_LOW, _HIGH)
    _set_state(env, qpos, qvel)
    expected, points = _pose_expected(goal, qpos, qvel)
    assert env.task.reward_terms == pytest.approx(expected, abs=1e-12)
    assert env.task.get_reward(env.physics) == pytest.approx(
      sum(expected.values()), abs=1e-12
    )
    assert float(_signal(env, 'score')) == pytest.approx(points, abs=1e-12)
    np.testing.assert_allclose(
      _signal(env, 'qpos_error'), goal - qpos, atol=1e-12
    )
  # The velocity penalty counts |qvel| >= pi only (pi itself included).
  fast = velocities[1][np.abs(velocities[1]) >= np.pi]
  assert fast.size == 5
  _set_state(env, goal, velocities[1])
  assert env.task.reward_terms['pose_error_cost'] == pytest.approx(0.0)
  assert env.task.reward_terms['joint_vel_cost'] == pytest.approx(
    -0.1 * np.linalg.norm(fast)
  )
  assert float(_signal(env, 'score')) == pytest.approx(1.0)


def test_pose_points_saturate_at_a_quarter_turn_error():
  env = suite.load('dclaw', 'pose_fixed', seed=0)
  env.reset()
  goal = env.task.goal
  _set_state(env, goal - 0.9, np.zeros(9))  # mean |error| 0.9 > pi/4
  assert float(_signal(env, 'score')) == 0.0
  _set_state(env, goal - np.pi / 8, np.zeros(9))
  assert float(_signal(env, 'score')) == pytest.approx(0.5)


def test_turn_terms_on_hand_built_states():
  env = suite.load('dclaw', 'turn_fixed', seed=0)
  env.reset()
  goal = np.pi  # ROBEL's TurnFixed goal.
  assert _wrap(env.task.goal - goal) == pytest.approx(0.0)
  rng = np.random.default_rng(6)
  valve_angles = [
    goal - 0.05,  # Both bonuses.
    goal + 0.2,  # Small bonus only.
    -np.pi + 0.3,  # 0.3 away across the +-pi seam.
    0.0,  # Half a turn away.
    goal + 6 * np.pi - 0.08,  # Unwrapped angle, both bonuses.
    -7.5,
  ]
  for angle in valve_angles:
    qpos = _RESET_POSE + rng.uniform(-0.3, 0.3, 9)
    qvel = rng.uniform(-1.5, 1.5, 9)
    _set_state(env, qpos, qvel, valve_qpos=angle, valve_qvel=3.0)
    expected, points = _valve_expected(goal, qpos, qvel, angle)
    assert env.task.reward_terms == pytest.approx(expected, abs=1e-9)
    assert env.task.get_reward(env.physics) == pytest.approx(
      sum(expected.values()), abs=1e-9
    )
    assert float(_signal(env, 'score')) == pytest.approx(points, abs=1e-9)
    np.testing.assert_allclose(_signal(env, 'object_x'), [math.cos(angle)])
    np.testing.assert_allclose(_signal(env, 'object_y'), [math.sin(angle)])
    error = float(_signal(env, 'target_error')[0])
    assert -np.pi <= error < np.pi
    assert _wrap(error - (goal - angle)) == pytest.approx(0.0, abs=1e-9)
  # Bonus boundaries: 10 below 0.25, 50 more below 0.1.
  for distance, small, big in ((0.24, 10, 0), (0.09, 10, 50),
                               (0.26, 0, 0)):  # fmt: skip
    _set_state(env, _RESET_POSE, np.zeros(9), valve_qpos=goal - distance)
    terms = env.task.reward_terms
    assert (terms['bonus_small'], terms['bonus_big']) == (small, big)
    assert terms['pose_diff_cost'] == pytest.approx(0.0, abs=1e-12)
    assert terms['joint_vel_cost'] == 0.0


def test_pose_success_is_the_running_mean_of_the_error():
  env = suite.load('dclaw', 'pose_fixed', seed=0)
  env.reset()
  goal = env.task.goal
  errors = [np.mean(np.abs(goal - _claw(env).qpos))]  # At reset.
  assert errors[0] > np.deg2rad(10)
  assert not _signal(env, 'success')
  held = 0.05  # rad per joint, well below 10 degrees.
  for _ in range(8):
    _set_state(env, goal - held, np.zeros(9))
    errors.append(held)
    running_mean = np.mean(errors)
    assert bool(_signal(env, 'success')) == (running_mean < np.deg2rad(10))
    # The score uses the current error only.
    assert float(_signal(env, 'score')) == pytest.approx(1 - held / (np.pi / 4))
  # It takes several steps at a small error to pull the mean below 10 deg.
  assert np.mean(errors[:2]) >= np.deg2rad(10)
  assert np.mean(errors) < np.deg2rad(10)
  assert _signal(env, 'success')


def test_turn_success_uses_the_current_error_only():
  env = suite.load('dclaw', 'turn_fixed', seed=0)
  env.reset()
  assert not _signal(env, 'success')  # Half a turn away at reset.
  for distance, success in ((0.05, True), (0.5, False), (0.099, True),
                            (0.101, False), (-0.05, True)):  # fmt: skip
    _set_state(env, _RESET_POSE, np.zeros(9), valve_qpos=np.pi - distance)
    assert bool(_signal(env, 'success')) == success, distance


def test_screw_success_is_the_running_mean_below_point_two():
  env = suite.load('dclaw', 'screw_fixed', seed=0)
  env.reset()
  assert env.task.goal == 0.0  # The goal starts at the valve's angle.
  errors = [0.0]
  for distance in (0.5, 0.5, 0.1, 0.0, 0.0):
    _set_state(env, _RESET_POSE, np.zeros(9), valve_qpos=-distance)
    errors.append(distance)
    assert bool(_signal(env, 'success')) == (np.mean(errors) < 0.2)
  # The third update had a current error of 0.1 but a mean of 0.275.
  assert [np.mean(errors[: i + 1]) < 0.2 for i in range(6)] == [
    True, False, False, False, False, True
  ]  # fmt: skip


def test_screw_goal_moves_unwrapped_at_half_a_radian_per_second():
  env = suite.load('dclaw', 'screw_fixed', seed=0)
  env.reset()
  for step in range(1, env.task.episode_steps + 1):
    timestep = env.step(np.zeros(9))
    assert env.task.goal == pytest.approx(0.5 * 0.1 * step)
  assert timestep.last()
  assert env.task.goal == pytest.approx(4.0)  # > pi: not wrapped.
  error = float(timestep.observation['target_error'][0])
  assert -np.pi <= error < np.pi


@pytest.mark.parametrize('valve_task_id', _VALVE_RANDOM_TASKS,
                         ids=_ids(_VALVE_RANDOM_TASKS))  # fmt: skip
def test_random_valve_initial_states_and_goals(valve_task_id):
  task_id = valve_task_id
  env = suite.load(*task_id, seed=0)
  screw = _family(task_id) == 'screw'
  initial, velocities = [], []
  for _ in range(15):
    env.reset()
    angle = float(_valve(env).qpos[0])
    goal = env.task.goal
    np.testing.assert_allclose(_claw(env).qpos, _RESET_POSE)
    assert _valve(env).qvel[0] == 0.0
    if screw:
      assert -np.pi <= angle <= np.pi
      assert goal == pytest.approx(angle)  # Goal starts at the valve.
      env.step(np.zeros(9))
      velocity = (env.task.goal - goal) / 0.1
      assert abs(velocity) <= 0.75
      velocities.append(velocity)
    else:
      assert -np.pi / 3 <= angle <= np.pi / 3
      assert -np.pi <= goal < np.pi  # Wrapped.
      assert abs(_wrap(goal - np.pi)) <= np.pi / 3 + 1e-12
    initial.append(angle)
  assert len(set(initial)) == len(initial)
  assert len(set(velocities)) == len(velocities)


_POSE_RANDOM_TASKS = tuple(
  t for t in suite.RANDOM + suite.RANDOM_DYNAMICS if _is_pose(t)
)


@pytest.mark.slow
@pytest.mark.parametrize('pose_task_id', _POSE_RANDOM_TASKS,
                         ids=_ids(_POSE_RANDOM_TASKS))  # fmt: skip
def test_random_pose_goal_oscillates_slowly_inside_the_pose_box(pose_task_id):
  # ROBEL's PoseRandom: start halfway between two random poses (in the box
  # top +-0.48, middle [-pi/3, 0], bottom +-pi/2); the goal oscillates
  # between them no faster than pi/6 rad/s per joint.
  low = np.tile([-0.48, -np.pi / 3, -np.pi / 2], 3)
  high = np.tile([0.48, 0.0, np.pi / 2], 3)
  env = suite.load(*pose_task_id, seed=0)
  starts = []
  for _ in range(3):
    env.reset()
    goal = env.task.goal
    np.testing.assert_allclose(goal, _claw(env).qpos)  # Goal(0) = start.
    starts.append(goal)
    moved = np.zeros(9)
    for _ in range(env.task.episode_steps):
      env.step(np.zeros(9))
      new_goal = env.task.goal
      assert np.all(new_goal >= low - 1e-12) and np.all(new_goal <= high)
      speed = np.abs(new_goal - goal) / env.control_timestep()
      assert np.all(speed <= np.pi / 6 + 1e-9)
      moved = np.maximum(moved, np.abs(new_goal - starts[-1]))
      goal = new_goal
    assert np.all(moved > 0)  # Every joint's goal moves.
  assert not np.array_equal(starts[0], starts[1])


@pytest.mark.slow
@pytest.mark.parametrize('pose_task_id', _POSE_RANDOM_TASKS,
                         ids=_ids(_POSE_RANDOM_TASKS))  # fmt: skip
def test_random_pose_goal_has_one_frequency_per_joint(pose_task_id):
  # ROBEL draws w_j ~ U(0.5, 2) rad/s for each of the nine joints and caps
  # each joint's amplitude at (pi/6) / w_j: the goal traces a Lissajous
  # curve, each joint no faster than 30 deg/s.
  env = suite.load(*pose_task_id, seed=1)
  max_speed = np.pi / 6
  for episode in range(200):
    env.reset()
    frequency, amplitude = env.task.goal_frequency, env.task.goal_amplitude
    assert frequency.shape == (9,)
    assert len(set(frequency.tolist())) == 9  # Nine different frequencies.
    assert np.all((frequency >= 0.5) & (frequency <= 2.0))
    assert np.all(amplitude * frequency <= max_speed + 1e-12)
    if episode >= 5:
      continue
    # The goal follows center + A_j sin(w_j t) joint by joint.
    center = env.task.goal
    goal = center
    for step in range(1, env.task.episode_steps + 1):
      env.step(env.task.normalize_joint_targets(center))
      time = step * env.control_timestep()
      expected = center + amplitude * np.sin(frequency * time)
      np.testing.assert_allclose(env.task.goal, expected, atol=1e-9)
      speed = np.abs(env.task.goal - goal) / env.control_timestep()
      assert np.all(speed <= max_speed + 1e-9)
      goal = env.task.goal


def test_fixed_valve_tasks_start_at_zero():
  for name, goal, velocity in (('turn_fixed', np.pi, 0.0),
                               ('screw_fixed', 0.0, 0.5)):  # fmt: skip
    env = suite.load('dclaw', name, seed=3)
    env.reset()
    assert _valve(env).qpos[0] == 0.0
    np.testing.assert_allclose(_claw(env).qpos, _RESET_POSE)
    assert _wrap(env.task.goal - goal) == pytest.approx(0.0)
    env.step(np.zeros(9))
    moved = env.task.goal - goal - velocity * 0.1
    assert _wrap(moved) == pytest.approx(0.0, abs=1e-12)


# --- The 4-prong valve -------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize('valve_task_id', _VALVE_TASKS, ids=_ids(_VALVE_TASKS))
def test_valve4_runs_an_episode(valve_task_id):
  env = suite.load(*valve_task_id, seed=0, task_kwargs={'valve': 'valve4'})
  assert env.task.valve.variant == 'valve4'
  timestep = env.reset()
  model = env.physics.model
  body = env.physics.bind(env.task.valve.valve_body).element_id
  geoms = np.flatnonzero(model.geom_bodyid == body)
  types = model.geom_type[geoms]
  capsules = geoms[types == 3]  # mjGEOM_CAPSULE
  assert len(capsules) == 2  # Two crossed bars: four prongs.
  assert np.count_nonzero(types == 5) == 1  # The hub cylinder.
  rng = np.random.default_rng(8)
  steps = 0
  while not timestep.last():
    timestep = env.step(rng.uniform(-1, 1, 9))
    steps += 1
    assert np.isfinite(timestep.reward)
  assert steps == env.task.episode_steps
  # The bars cross at right angles (their axes are the geoms' z axes).
  axes = env.physics.data.geom_xmat[capsules].reshape(2, 3, 3)[:, :, 2]
  assert abs(np.dot(axes[0], axes[1])) < 1e-9
  assert np.all(np.abs(axes[:, 2]) < 1e-9)  # Both horizontal.


def test_valve3_is_the_default():
  env = suite.load('dclaw', 'turn_fixed', seed=0)
  assert env.task.valve.variant == 'valve3'
  model = env.physics.model
  body = env.physics.bind(env.task.valve.valve_body).element_id
  geoms = np.flatnonzero(model.geom_bodyid == body)
  assert np.count_nonzero(model.geom_type[geoms] == 3) == 3


@pytest.mark.parametrize('valve', ['valve3', 'valve4'])
def test_valve_turns_freely(valve):
  env = suite.load('dclaw', 'turn_fixed', seed=0, task_kwargs={'valve': valve})
  env.reset()
  hinge = _valve(env)
  assert not env.physics.model.jnt_limited[hinge.element_id]
  hinge.qpos = 10.0
  hold = _RESET_POSE / _HALF_RANGE
  timestep = env.step(hold)
  angle = float(hinge.qpos[0])
  assert abs(angle - 10.0) < 0.05
  obs = timestep.observation
  np.testing.assert_allclose(obs['object_x'], [math.cos(angle)])
  np.testing.assert_allclose(obs['object_y'], [math.sin(angle)])
  expected_error = _wrap(np.pi - angle)
  assert float(obs['target_error'][0]) == pytest.approx(expected_error)
