"""Tests of the D'Kitty tasks against ROBEL's definitions.

Expected values are computed here, independently of robel_dm, from the
formulas and constants of docs/robel_reference.md (sections 2.4-2.7): torso
observations, reward terms, scores, success, falling, initial states and
goals, the terrain, and that the robot stands. Hand-built states are written
into the free joint and the leg joints directly. What every task shares
(observation layout, action map, safety counters) is in test_tasks.py;
dynamics randomization and noise in test_randomization.py.
"""

import math

from dm_control import mjcf
import mujoco
import numpy as np
import pytest
import robel_spec

from robel_dm import geometry, suite

_ORIGIN = np.array([0.0, 0.0, 0.3])  # ROBEL's kitty_frame start.
_STANDING = np.zeros(12)
_CROUCH = np.tile([0.0, np.pi / 4, -np.pi / 2], 4)  # ROBEL's StandFixed.
# Falling: upright threshold and falling term per family
# (docs/robel_reference.md section 2.4).
_FALLING = {'stand': (0.0, -100.0), 'orient': (0.9, -500.0),
            'walk': (0.9, -500.0)}  # fmt: skip


# --- Rotations, independent of robel_dm ---------------------------------------


def _rot_x(angle):
  c, s = math.cos(angle), math.sin(angle)
  return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(angle):
  c, s = math.cos(angle), math.sin(angle)
  return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(angle):
  c, s = math.cos(angle), math.sin(angle)
  return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


_TILTS = {'x': _rot_x, 'y': _rot_y}


def _pose(yaw=0.0, tilt_axis='x', tilt=0.0):
  """Torso-to-world rotation: turned by `yaw`, then tilted about its own
  x (pitch) or y (roll) axis."""
  return _rot_z(yaw) @ _TILTS[tilt_axis](tilt)


def _quaternion(rotation):
  quat = np.zeros(4)
  mujoco.mju_mat2Quat(quat, np.asarray(rotation, float).ravel())
  return quat


def _wrap(angle):
  return float(np.angle(np.exp(1j * angle)))


# --- Environment access -------------------------------------------------------


def _root(env):
  """The D'Kitty's free joint, bound to the physics."""
  return env.physics.bind(mjcf.get_frame_freejoint(env.task.robot.mjcf_model))


def _legs(env):
  return env.physics.bind(env.task.robot.joints)


def _torso(env):
  return env.physics.bind(env.task.robot.torso)


def _signal(env, name):
  """The current value of a task observable (also disabled ones)."""
  return np.array(env.task.task_observables[name](env.physics))


def _set_state(env, position, rotation=None, legs=_STANDING, qvel=None):
  """Writes a hand-built state and recomputes the task's signals from it.

  Args:
    env: a D'Kitty environment, reset.
    position: torso position in the world, m.
    rotation: torso-to-world rotation; level, facing +y if None.
    legs: the 12 leg joint angles, rad.
    qvel: the free joint's 6 velocities (MuJoCo's convention); zero if None.
  """
  rotation = np.eye(3) if rotation is None else rotation
  root = _root(env)
  root.qpos = np.concatenate([position, _quaternion(rotation)])
  root.qvel = np.zeros(6) if qvel is None else qvel
  _legs(env).qpos = legs
  _legs(env).qvel = np.zeros(12)
  env.physics.forward()
  env.task._update(env.physics, env.random_state)


def _hold(env):
  """The action that commands the legs' current angles."""
  return env.task.normalize_joint_targets(_legs(env).qpos.copy())


def _standing_action(env):
  return env.task.normalize_joint_targets(_STANDING)


@pytest.fixture(scope='module')
def kitty_envs():
  """The fixed tasks' environments, loaded once for this module."""
  envs = {
    family: suite.load('dkitty', f'{family}_fixed', seed=0)
    for family in ('stand', 'orient', 'walk')
  }
  yield envs
  for env in envs.values():
    env.close()


# --- ROBEL's rewards (docs/robel_reference.md sections 2.5-2.7) ---------------


def _stand_expected(upright, legs, xy):
  e, c = np.mean(np.abs(legs)), np.linalg.norm(xy)
  terms = {
    'upright': 2 * upright,
    'falling': -100.0 * (upright < 0),
    'pose_error_cost': -4 * e,
    'center_distance_cost': -2 * c,
    'bonus_small': 5 * (e < np.pi / 6) * upright,
    'bonus_big': 10.0 * (e < np.pi / 12) * (upright > 0.9),
  }
  # robel_dm writes min() where ROBEL wrote max() (always <= 0).
  points = (1 - min(e / (np.pi / 3), 1)) * upright
  return terms, points


def _orient_expected(upright, angle_error, xy):
  a, c = angle_error, np.linalg.norm(xy)
  terms = {
    'upright': 2 * (upright - 0.9) / 0.1,
    'falling': -500.0 * (upright < 0.9),
    'alignment_error_cost': -4 * a,
    'center_distance_cost': -4 * c,
    # ROBEL's `+` of two boolean arrays is a logical OR: 0 or 5, never 10.
    'bonus_small': 5.0 * ((a < 0.26) or (upright > 0.96)),
    'bonus_big': 10.0 * (a < 0.087) * (upright > 0.96),
  }
  return terms, 1 - a / np.pi


def _walk_expected(upright, heading, distance):
  h, d = heading, distance
  terms = {
    'upright': (upright - 0.9) / 0.1,
    'falling': -500.0 * (upright < 0.9),
    'target_dist_cost': -4 * d,
    'heading': 2 * (h - 0.9) / 0.1,
    'bonus_small': 5.0 * ((d < 0.5) or (h > 0.9)),
    'bonus_big': 10.0 * (d < 0.5) * (h > 0.9),
  }
  return terms, -d


def _assert_signals(env, terms, points, upright, threshold):
  """Compares the task's uprightness, terms, reward, score, success and
  failure with the expected ones."""
  assert float(_signal(env, 'upright')[0]) == pytest.approx(upright, abs=1e-12)
  assert tuple(env.task.reward_terms) == tuple(terms)
  for name, value in terms.items():
    assert env.task.reward_terms[name] == pytest.approx(value, abs=1e-9), name
  reward = env.task.get_reward(env.physics)
  assert reward == pytest.approx(sum(terms.values()), abs=1e-9)
  assert float(_signal(env, 'score')) == pytest.approx(points, abs=1e-9)
  assert bool(_signal(env, 'success')) == (terms['bonus_big'] > 0)
  fallen = upright < threshold
  assert env.task._failed == fallen
  assert env.task.should_terminate_episode(env.physics) == fallen
  assert env.task.get_discount(env.physics) == (0.0 if fallen else 1.0)


# Stand states: torso xy, yaw, tilt axis and angle, mean |joint error| of
# legs with mixed signs.
_STAND_STATES = [
  ((0.0, 0.0), 0.0, 'x', 0.0, 0.0),  # Standing straight: both bonuses.
  ((0.1, -0.2), 0.3, 'x', 0.5, 0.2),  # u 0.878: no big bonus.
  ((0.0, 0.05), -1.0, 'y', 0.4, 0.4),  # e > pi/12: small bonus only.
  ((0.0, 0.0), 0.0, 'y', 0.44, 0.26),  # u 0.905, e just < pi/12: both.
  ((0.0, 0.0), 0.0, 'y', 0.46, 0.1),  # u 0.896: no big bonus.
  ((0.0, 0.0), 0.0, 'x', 0.0, 0.265),  # e just > pi/12.
  ((0.0, 0.0), 0.0, 'x', 0.0, 0.52),  # e just < pi/6: small bonus.
  ((0.0, 0.0), 0.0, 'x', 0.0, 0.53),  # e just > pi/6: no bonus.
  ((0.3, 0.4), 2.0, 'x', 0.0, 1.2),  # e > pi/3: the points saturate at 0.
  ((0.0, 0.0), 0.0, 'y', 1.7, 0.0),  # u -0.129: fallen.
  ((0.0, 0.0), 0.0, 'x', np.pi, 0.3),  # Upside down.
]


def test_stand_terms_on_hand_built_states(kitty_envs):
  env = kitty_envs['stand']
  env.reset()
  signs = np.resize([1.0, -1.0, -1.0], 12)
  for xy, yaw, axis, tilt, error in _STAND_STATES:
    legs = error * signs
    position = np.array([*xy, 0.3])
    _set_state(env, position, _pose(yaw, axis, tilt), legs)
    upright = math.cos(tilt)
    terms, points = _stand_expected(upright, legs, xy)
    _assert_signals(env, terms, points, upright, threshold=0.0)
    np.testing.assert_allclose(_signal(env, 'pose_error'), -legs, atol=1e-12)
  # The test's own data covers every bonus combination, the points'
  # saturation and a fall.
  cases = []
  for xy, _, _, tilt, error in _STAND_STATES:
    terms, points = _stand_expected(math.cos(tilt), error * signs, xy)
    cases.append((terms['bonus_small'] > 0, terms['bonus_big'] > 0,
                  points == 0, terms['falling'] < 0))  # fmt: skip
  assert {case[:2] for case in cases} == {(True, True), (True, False),
                                          (False, False)}  # fmt: skip
  assert any(case[2] for case in cases) and any(case[3] for case in cases)


def test_stand_terms_with_random_legs(kitty_envs):
  env = kitty_envs['stand']
  env.reset()
  rng = np.random.default_rng(0)
  for _ in range(5):
    legs = rng.uniform(robel_spec.DKITTY_ACTION_LOW,
                       robel_spec.DKITTY_ACTION_HIGH)  # fmt: skip
    xy = rng.uniform(-0.5, 0.5, 2)
    tilt = rng.uniform(0, 0.6)
    _set_state(env, [*xy, 0.25], _pose(rng.uniform(-3, 3), 'y', tilt), legs)
    upright = math.cos(tilt)
    terms, points = _stand_expected(upright, legs, xy)
    _assert_signals(env, terms, points, upright, threshold=0.0)


# Orient states (orient_fixed: the target is at (0, -1)): torso xy, yaw,
# tilt axis and angle. The torso faces along yaw + pi/2 for tilts < 90 deg.
_ORIENT_STATES = [
  ((0.0, 0.0), np.pi, 'x', 0.0),  # Facing the target: both bonuses.
  ((0.0, 0.0), np.pi + 0.2, 'y', 0.25),  # a 0.2, u 0.969: small 5.
  ((0.0, 0.0), np.pi - 0.05, 'x', 0.3),  # u 0.955: small 5, no big.
  ((0.0, 0.0), np.pi - 0.08, 'y', 0.2),  # a 0.08 < 0.087: both bonuses.
  ((0.0, 0.0), np.pi + 0.09, 'y', 0.0),  # a 0.09 > 0.087: small only.
  ((0.3, 0.2), np.pi - 0.1, 'x', 0.1),  # Off centre.
  ((0.0, 0.0), 0.0, 'x', 0.0),  # Facing away: points 0.
  ((0.0, 0.0), np.pi / 2, 'y', 0.0),  # Facing -x: a = pi/2.
  ((-0.2, 0.1), np.pi, 'y', 0.5),  # u 0.878: fallen.
]


def test_orient_terms_on_hand_built_states(kitty_envs):
  env = kitty_envs['orient']
  env.reset()
  target = np.array([0.0, -1.0])
  np.testing.assert_allclose(env.task.target, target, atol=1e-12)
  for xy, yaw, axis, tilt in _ORIENT_STATES:
    _set_state(env, [*xy, 0.3], _pose(yaw, axis, tilt))
    upright = math.cos(tilt)
    to_target = target - xy
    desired = math.atan2(to_target[1], to_target[0])
    angle_error = abs(_wrap(desired - (yaw + np.pi / 2)))
    terms, points = _orient_expected(upright, angle_error, xy)
    _assert_signals(env, terms, points, upright, threshold=0.9)
    facing = _pose(yaw, axis, tilt)[:2, 1]
    np.testing.assert_allclose(_signal(env, 'current_facing'), facing,
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(
      _signal(env, 'desired_facing'),
      to_target / np.linalg.norm(to_target),
      atol=1e-12,
    )
    assert float(_signal(env, 'angle_error')[0]) == pytest.approx(
      angle_error, abs=1e-9
    )


# Walk states (walk_fixed: the target is at (0, 2)): torso xy, yaw, tilt.
_WALK_STATES = [
  ((0.0, 0.0), 0.0, 'x', 0.0),  # Facing the target 2 m away.
  ((0.1, 1.7), 0.1, 'y', 0.0),  # Near and facing it: both bonuses.
  ((0.3, 1.8), -np.pi / 2, 'x', 0.0),  # Near, facing +x: h < 0.
  ((0.0, 1.6), 0.0, 'x', 0.3),  # Near, u 0.955: both bonuses.
  ((0.6, 2.0), np.pi / 2, 'y', 0.2),  # Facing it, 0.6 m away: small 5.
  ((0.0, 1.0), 0.5, 'y', 0.0),  # h = cos(0.5) 0.878 < 0.9, 1 m away.
  ((0.2, 0.5), 0.0, 'y', 0.5),  # u 0.878: fallen.
]


def test_walk_terms_on_hand_built_states(kitty_envs):
  env = kitty_envs['walk']
  env.reset()
  target = np.array([0.0, 2.0])
  np.testing.assert_allclose(env.task.target, target, atol=1e-12)
  for xy, yaw, axis, tilt in _WALK_STATES:
    _set_state(env, [*xy, 0.3], _pose(yaw, axis, tilt))
    upright = math.cos(tilt)
    error = target - xy
    heading = math.cos(math.atan2(error[1], error[0]) - (yaw + np.pi / 2))
    terms, points = _walk_expected(upright, heading, np.linalg.norm(error))
    _assert_signals(env, terms, points, upright, threshold=0.9)
    assert float(_signal(env, 'heading')[0]) == pytest.approx(heading)
    np.testing.assert_allclose(_signal(env, 'target_error'), error, atol=1e-12)
    np.testing.assert_allclose(_signal(env, 'target_pos'), target, atol=1e-12)


# The small bonus pays 5 when either condition holds and never 10 (ROBEL's
# logical OR); exact values, not the formula above. Orient: yaw offset from
# facing the target (= angle error), tilt about the torso's y axis (keeps
# the facing direction); Walk: torso xy and yaw.
_ORIENT_BONUSES = [
  (0.0, 0.0, 5.0, 10.0),  # a 0, u 1: both conditions and the big bonus.
  (0.2, 0.0, 5.0, 0.0),  # a 0.2 < 0.26 and u 1 > 0.96: still 5.
  (0.2, 0.35, 5.0, 0.0),  # u 0.939: the angle alone.
  (0.5, 0.0, 5.0, 0.0),  # a 0.5: uprightness alone.
  (0.5, 0.35, 0.0, 0.0),  # Neither.
]
_WALK_BONUSES = [
  ((0.0, 1.7), 0.0, 5.0, 10.0),  # Near (0.3 m) and facing: both.
  ((0.3, 1.8), -np.pi / 2, 5.0, 0.0),  # Near, facing away.
  ((0.0, 0.0), 0.0, 5.0, 0.0),  # Facing, 2 m away.
  ((0.0, 0.0), np.pi / 2, 0.0, 0.0),  # Neither.
]


def test_orient_small_bonus_is_a_logical_or(kitty_envs):
  env = kitty_envs['orient']
  env.reset()
  for offset, tilt, small, big in _ORIENT_BONUSES:
    _set_state(env, [0.0, 0.0, 0.3], _pose(np.pi + offset, 'y', tilt))
    assert float(_signal(env, 'angle_error')[0]) == pytest.approx(offset)
    terms = env.task.reward_terms
    assert (terms['bonus_small'], terms['bonus_big']) == (small, big)


def test_walk_small_bonus_is_a_logical_or(kitty_envs):
  env = kitty_envs['walk']
  env.reset()
  for xy, yaw, small, big in _WALK_BONUSES:
    _set_state(env, [*xy, 0.3], _pose(yaw))
    terms = env.task.reward_terms
    assert (terms['bonus_small'], terms['bonus_big']) == (small, big)


def _expected_from_physics(env, family):
  """ROBEL's terms and points of the current (true) physics state."""
  torso = _torso(env)
  upright, xy = float(torso.xmat[8]), torso.xpos[:2].copy()
  facing = torso.xmat[[1, 4]]  # The torso's y axis on the floor.
  if family == 'stand':
    return _stand_expected(upright, _legs(env).qpos.copy(), xy)
  to_target = env.task.target - xy
  cosine = np.dot(facing, to_target) / (
    np.linalg.norm(facing) * np.linalg.norm(to_target)
  )
  if family == 'orient':
    return _orient_expected(upright, math.acos(np.clip(cosine, -1, 1)), xy)
  return _walk_expected(upright, cosine, np.linalg.norm(to_target))


def test_reward_is_the_sum_of_robels_terms_on_real_steps(dkitty_task_id):
  env = suite.load(*dkitty_task_id, seed=0)
  family = robel_spec.family(dkitty_task_id)
  threshold, _ = _FALLING[family]
  timestep = env.reset()
  policy = robel_spec.steady_policy(env, seed=4, noise=0.3)
  for _ in range(12):
    timestep = env.step(policy(timestep))
    terms, points = _expected_from_physics(env, family)
    upright = float(_torso(env).xmat[8])
    _assert_signals(env, terms, points, upright, threshold)
    assert timestep.reward == pytest.approx(sum(terms.values()), abs=1e-9)
    assert float(timestep.observation['score']) == pytest.approx(points)
    if timestep.last():
      break


# --- Torso observations -------------------------------------------------------


@pytest.mark.parametrize(
  'rotation, upright',
  [
    (np.eye(3), 1.0),
    (_rot_x(np.pi), -1.0),
    (_rot_y(np.pi), -1.0),
    (_rot_x(np.pi / 6), math.cos(np.pi / 6)),
    (_rot_y(-0.9), math.cos(0.9)),
    (_rot_z(1.0) @ _rot_x(2.0), math.cos(2.0)),
    (_rot_z(-2.5) @ _rot_y(0.3) @ _rot_x(0.4), math.cos(0.3) * math.cos(0.4)),
  ],
  ids=['level', 'flipped_x', 'flipped_y', 'tilt_30', 'roll_0.9', 'tilt_2',
       'tilt_both'],
)  # fmt: skip
def test_upright_is_the_cosine_of_the_tilt(rotation, upright, kitty_envs):
  for env in kitty_envs.values():
    env.reset()
    _set_state(env, _ORIGIN, rotation)
    assert float(_signal(env, 'upright')[0]) == pytest.approx(
      upright, abs=1e-12
    )


@pytest.mark.parametrize(
  'yaw, facing',
  [
    (np.pi / 2, (-1.0, 0.0)),  # A quarter turn left: facing -x.
    (-np.pi / 2, (1.0, 0.0)),
    (np.pi - 0.1, (-math.sin(0.1), -math.cos(0.1))),
    (0.7, (-math.sin(0.7), math.cos(0.7))),
  ],
  ids=['left', 'right', 'almost_around', '0.7'],
)
def test_facing_and_heading_of_a_turned_robot(yaw, facing, kitty_envs):
  orient, walk = kitty_envs['orient'], kitty_envs['walk']
  for env in (orient, walk):
    env.reset()
    _set_state(env, _ORIGIN, _rot_z(yaw))
    np.testing.assert_allclose(_signal(env, 'root_euler'), [0.0, 0.0, yaw],
                               atol=1e-12)  # fmt: skip
  # Orient's target is at (0, -1): heading -pi/2 from the origin.
  np.testing.assert_allclose(_signal(orient, 'current_facing'), facing,
                             atol=1e-12)  # fmt: skip
  np.testing.assert_allclose(_signal(orient, 'desired_facing'), [0, -1],
                             atol=1e-12)  # fmt: skip
  angle_error = abs(_wrap(-np.pi / 2 - (yaw + np.pi / 2)))
  assert float(_signal(orient, 'angle_error')[0]) == pytest.approx(angle_error)
  # Walk's target is at (0, 2): straight ahead at yaw 0.
  heading = float(_signal(walk, 'heading')[0])
  assert heading == pytest.approx(math.cos(yaw), abs=1e-12)
  assert heading == pytest.approx(facing[1], abs=1e-12)


def test_root_position_is_relative_to_robels_frame_origin(kitty_envs):
  for env in kitty_envs.values():
    env.reset()
    _set_state(env, [0.2, -0.1, 0.45])
    np.testing.assert_allclose(
      _signal(env, 'root_pos'), [0.2, -0.1, 0.15], atol=1e-12
    )
    np.testing.assert_allclose(_torso(env).xpos, [0.2, -0.1, 0.45])


def test_root_euler_is_robels_rotating_xyz(kitty_envs):
  env = kitty_envs['walk']
  env.reset()
  rng = np.random.default_rng(1)
  for _ in range(10):
    a, c = rng.uniform(-np.pi, np.pi, 2)
    b = rng.uniform(-1.5, 1.5)
    _set_state(env, _ORIGIN, _rot_x(a) @ _rot_y(b) @ _rot_z(c))
    np.testing.assert_allclose(_signal(env, 'root_euler'), [a, b, c],
                               atol=1e-9)  # fmt: skip


def test_euler_xyz_inverts_rx_ry_rz():
  rng = np.random.default_rng(2)
  for _ in range(200):
    a, c = rng.uniform(-np.pi, np.pi, 2)
    b = rng.uniform(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3)
    rotation = _rot_x(a) @ _rot_y(b) @ _rot_z(c)
    angles = geometry.euler_xyz(rotation)
    np.testing.assert_allclose(angles, [a, b, c], atol=1e-9)
    # Nested lists work as well as arrays.
    assert geometry.euler_xyz(rotation.tolist()) == pytest.approx(angles)


def _rotation_exp(omega, t):
  """exp(t [omega]x) by Rodrigues' formula."""
  angle = np.linalg.norm(omega) * t
  axis = omega / np.linalg.norm(omega)
  k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]],
                [-axis[1], axis[0], 0]])  # fmt: skip
  return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def test_euler_xyz_rates_match_finite_differences():
  # A body turning at a constant world angular velocity omega:
  # R(t) = exp(t [omega]x) R0; its Euler angles change at euler_xyz_rates.
  rng = np.random.default_rng(3)
  h = 1e-6
  for _ in range(50):
    a, c = rng.uniform(-np.pi, np.pi, 2)
    b = rng.uniform(-1.3, 1.3)
    start = _rot_x(a) @ _rot_y(b) @ _rot_z(c)
    omega = rng.uniform(-3, 3, 3)
    after = np.array(geometry.euler_xyz(_rotation_exp(omega, h) @ start))
    before = np.array(geometry.euler_xyz(_rotation_exp(omega, -h) @ start))
    expected = [_wrap(d) / (2 * h) for d in after - before]
    rates = geometry.euler_xyz_rates((a, b, c), omega)
    np.testing.assert_allclose(rates, expected, rtol=1e-6, atol=1e-6)


def _integrated_pose(env, qpos, qvel, dt):
  """Free-joint position and rotation after moving at `qvel` for `dt`
  (MuJoCo's own integration, whatever its velocity convention)."""
  moved = qpos.copy()
  mujoco.mj_integratePos(env.physics.model.ptr, moved, qvel, dt)
  root = _root(env)
  address = int(root.qposadr)
  rotation = np.zeros(9)
  mujoco.mju_quat2Mat(rotation, moved[address + 3 : address + 7])
  return moved[address : address + 3], rotation.reshape(3, 3)


def test_root_velocities_are_world_velocity_and_euler_rates(kitty_envs):
  env = kitty_envs['orient']
  env.reset()
  rng = np.random.default_rng(4)
  h = 1e-6
  for _ in range(10):
    a, c = rng.uniform(-np.pi, np.pi, 2)
    b = rng.uniform(-1.2, 1.2)
    root_qvel = rng.uniform(-2, 2, 6)
    _set_state(
      env, [0.1, 0.2, 0.3], _rot_x(a) @ _rot_y(b) @ _rot_z(c), qvel=root_qvel
    )
    qpos, qvel = env.physics.data.qpos.copy(), env.physics.data.qvel.copy()
    position_after, after = _integrated_pose(env, qpos, qvel, h)
    position_before, before = _integrated_pose(env, qpos, qvel, -h)
    velocity = (position_after - position_before) / (2 * h)
    rates = [
      _wrap(d) / (2 * h)
      for d in np.subtract(
        geometry.euler_xyz(after), geometry.euler_xyz(before)
      )
    ]
    np.testing.assert_allclose(_signal(env, 'root_vel'), velocity, atol=1e-6)
    np.testing.assert_allclose(
      _signal(env, 'root_angular_vel'), rates, rtol=1e-5, atol=1e-5
    )


# --- Falling ------------------------------------------------------------------


@pytest.mark.parametrize(
  'family, rotation, falls',
  [
    ('stand', _rot_x(np.pi), True),
    ('stand', _rot_y(np.pi), True),
    ('stand', _rot_x(np.pi / 3), False),  # Stand falls at 90 degrees only.
    ('orient', _rot_x(np.pi / 3), True),
    ('orient', _rot_y(np.pi), True),
    ('walk', _rot_y(np.pi / 3), True),
    ('walk', _rot_x(np.pi), True),
  ],
  ids=['stand-flipped_x', 'stand-flipped_y', 'stand-tilt_60',
       'orient-tilt_60', 'orient-flipped_y', 'walk-roll_60',
       'walk-flipped_x'],
)  # fmt: skip
def test_falling_ends_the_episode_with_discount_zero(
  family, rotation, falls, kitty_envs
):
  env = kitty_envs[family]
  threshold, falling = _FALLING[family]
  timestep = env.reset()
  for _ in range(3):
    timestep = env.step(_hold(env))
    assert timestep.mid() and timestep.discount == 1.0
  # Tip the robot over (where it stands), then take a step.
  _set_state(env, _torso(env).xpos.copy(), rotation, _legs(env).qpos.copy())
  timestep = env.step(_hold(env))
  upright = float(timestep.observation['upright'][0])
  terms = env.task.reward_terms
  assert timestep.reward == pytest.approx(sum(terms.values()), abs=1e-12)
  if not falls:
    assert threshold <= upright < 0.9
    assert timestep.mid() and timestep.discount == 1.0
    assert terms['falling'] == 0.0
    return
  assert upright < threshold
  assert timestep.last()
  assert timestep.discount == 0.0
  assert terms['falling'] == falling
  # The next step starts a new episode, upright again.
  timestep = env.step(_hold(env))
  assert timestep.first()
  assert timestep.reward is None and timestep.discount is None
  assert env.physics.data.time == 0.0
  assert float(timestep.observation['upright'][0]) > 0.99
  assert env.step(_hold(env)).mid()


def test_discount_is_zero_exactly_when_the_robot_has_fallen(dkitty_task_id):
  # Random bang-bang actions topple the D'Kitty in about half the episodes
  # (or more); only a fall gives discount 0.
  env = suite.load(*dkitty_task_id, seed=1)
  threshold, falling = _FALLING[robel_spec.family(dkitty_task_id)]
  rng = np.random.default_rng(5)
  timestep = env.reset()
  falls = episodes = 0
  while falls < 2 and episodes < 8:
    timestep = env.step(rng.choice([-1.0, 1.0], 12))
    if timestep.first():
      episodes += 1
      continue
    fallen = float(timestep.observation['upright'][0]) < threshold
    assert timestep.discount == (0.0 if fallen else 1.0)
    assert env.task.reward_terms['falling'] == (falling if fallen else 0.0)
    if fallen:
      assert timestep.last()
      falls += 1
    elif timestep.last():
      assert env.physics.data.time == pytest.approx(env.task.time_limit)
  assert falls >= 1, 'the robot never fell'


# --- Initial states and goals -------------------------------------------------


def test_stand_fixed_starts_settled_in_robels_crouch(kitty_envs):
  env = kitty_envs['stand']
  for _ in range(2):
    timestep = env.reset()
    obs = timestep.observation
    assert env.physics.data.time == 0.0  # The settling is not in the episode.
    np.testing.assert_allclose(_legs(env).qpos, _CROUCH, atol=0.03)
    np.testing.assert_allclose(obs['kitty_qpos'], _legs(env).qpos)
    # ROBEL's compiled crouch settles at a torso height of 0.244 m.
    assert _torso(env).xpos[2] == pytest.approx(0.244, abs=0.005)
    assert obs['root_pos'][2] == pytest.approx(0.244 - 0.3, abs=0.005)
    np.testing.assert_allclose(obs['root_pos'][:2], 0.0, atol=0.01)
    assert obs['upright'][0] > 0.999
    # It has settled: it barely moves any more.
    assert np.abs(obs['root_vel']).max() < 0.01
    assert np.abs(obs['kitty_qvel']).max() < 0.1
    np.testing.assert_array_equal(obs['last_action'], 0.0)
    for _ in range(3):
      env.step(_hold(env))


def test_stand_random_starts_from_a_pose_in_the_action_ranges():
  low, high = robel_spec.DKITTY_ACTION_LOW, robel_spec.DKITTY_ACTION_HIGH
  env = suite.load('dkitty', 'stand_random', seed=3)
  poses = []
  for _ in range(20):
    env.reset()
    assert env.physics.data.time == 0.0
    # The reset commanded the drawn pose while the robot settled.
    pose = env.physics.bind(env.task.robot.actuators).ctrl.copy()
    assert np.all(pose >= low) and np.all(pose <= high)
    assert np.abs(_legs(env).qpos - pose).max() < 0.5
    assert _torso(env).xpos[2] < 0.3  # Settled onto the floor.
    poses.append(pose)
  poses = np.array(poses)
  # Every joint spreads over its action range.
  assert np.all((poses.max(0) - poses.min(0)) > 0.5 * (high - low))


def test_stand_reset_starts_from_the_initial_pose_and_settles():
  # The same draws with and without settling: without, the episode starts
  # exactly in the drawn pose, placed still at ROBEL's frame origin.
  drawn = suite.load(
    'dkitty', 'stand_random', seed=3, task_kwargs={'settle_substeps': 0}
  )
  settled = suite.load('dkitty', 'stand_random', seed=3)
  assert drawn.task.settle_substeps == 0
  assert settled.task.settle_substeps == 140  # ROBEL's 40 + 100.
  for _ in range(3):
    drawn.reset()
    settled.reset()
    pose = settled.physics.bind(settled.task.robot.actuators).ctrl.copy()
    np.testing.assert_array_equal(_legs(drawn).qpos, pose)
    np.testing.assert_array_equal(_legs(drawn).qvel, 0.0)
    np.testing.assert_array_equal(_torso(drawn).xpos, _ORIGIN)
    np.testing.assert_array_equal(_root(drawn).qvel, 0.0)
    assert drawn.physics.data.time == settled.physics.data.time == 0.0


def test_orient_fixed_faces_plus_y_with_the_target_behind(kitty_envs):
  env = kitty_envs['orient']
  for _ in range(2):
    obs = env.reset().observation
    np.testing.assert_allclose(env.task.target, [0.0, -1.0], atol=1e-12)
    np.testing.assert_array_equal(obs['root_pos'], 0.0)
    np.testing.assert_array_equal(obs['root_euler'], 0.0)
    np.testing.assert_allclose(obs['current_facing'], [0, 1], atol=1e-12)
    np.testing.assert_allclose(obs['desired_facing'], [0, -1], atol=1e-12)
    np.testing.assert_array_equal(obs['kitty_qpos'], _STANDING)
    np.testing.assert_array_equal(obs['kitty_qvel'], 0.0)
    np.testing.assert_array_equal(obs['root_vel'], 0.0)
    assert float(_signal(env, 'angle_error')[0]) == pytest.approx(np.pi)
    _assert_marker(env, 'target', [0.0, -1.0])
    env.step(_standing_action(env))


def _assert_marker(env, name, xy):
  model = env.physics.model
  mocap = model.body_mocapid[model.name2id(name, 'body')]
  np.testing.assert_allclose(env.physics.data.mocap_pos[mocap, :2], xy,
                             atol=1e-12)  # fmt: skip


def _heading_from_plus_y(xy):
  """Heading of a direction, counted from +y counter-clockwise, [0, 2pi)."""
  return (math.atan2(xy[1], xy[0]) - np.pi / 2) % (2 * np.pi)


@pytest.mark.parametrize('task', ['orient_random', 'orient_random_dynamics'])
def test_orient_random_draws_robels_headings(task):
  env = suite.load('dkitty', task, seed=0)
  yaws, target_headings = [], []
  for _ in range(30):
    obs = env.reset().observation
    target = env.task.target
    yaw = float(obs['root_euler'][2])
    assert -np.pi / 3 <= yaw <= np.pi / 3
    np.testing.assert_allclose(
      obs['current_facing'], [-math.sin(yaw), math.cos(yaw)], atol=1e-12
    )
    assert np.linalg.norm(target) == pytest.approx(1.0)
    heading = _heading_from_plus_y(target)
    assert 2 * np.pi / 3 <= heading <= 4 * np.pi / 3
    np.testing.assert_allclose(obs['desired_facing'], target, atol=1e-12)
    np.testing.assert_array_equal(obs['root_pos'], 0.0)
    _assert_marker(env, 'target', target)
    yaws.append(yaw)
    target_headings.append(heading)
  assert _spread(yaws, 2 * np.pi / 3) > 0.6
  assert _spread(target_headings, 2 * np.pi / 3) > 0.6


def _spread(values, width):
  return (max(values) - min(values)) / width


def test_walk_fixed_target_is_two_metres_ahead(kitty_envs):
  env = kitty_envs['walk']
  for _ in range(2):
    obs = env.reset().observation
    np.testing.assert_allclose(env.task.target, [0.0, 2.0], atol=1e-12)
    np.testing.assert_allclose(obs['target_error'], [0.0, 2.0], atol=1e-12)
    assert float(obs['heading'][0]) == pytest.approx(1.0)
    np.testing.assert_array_equal(obs['root_pos'], 0.0)
    np.testing.assert_array_equal(obs['root_euler'], 0.0)
    np.testing.assert_array_equal(obs['kitty_qpos'], _STANDING)
    _assert_marker(env, 'target', [0.0, 2.0])
    _assert_marker(env, 'heading', [0.0, 2.0])
    env.step(_standing_action(env))


@pytest.mark.parametrize('task', ['walk_random', 'walk_random_dynamics'])
def test_walk_random_draws_robels_targets(task):
  env = suite.load('dkitty', task, seed=0)
  distances, angles = [], []
  for _ in range(30):
    obs = env.reset().observation
    target = env.task.target
    distance = np.linalg.norm(target)
    angle = math.atan2(target[1], target[0])
    assert 1.0 <= distance <= 2.0
    assert np.pi / 2 - np.pi / 3 <= angle <= np.pi / 2 + np.pi / 3
    np.testing.assert_allclose(obs['target_error'], target, atol=1e-12)
    assert float(obs['heading'][0]) == pytest.approx(math.sin(angle))
    _assert_marker(env, 'target', target)
    distances.append(distance)
    angles.append(angle)
  assert _spread(distances, 1.0) > 0.6
  assert _spread(angles, 2 * np.pi / 3) > 0.6


def test_every_episode_starts_at_time_zero(dkitty_task_id, shared_env):
  env = shared_env(dkitty_task_id)
  timestep = env.reset()
  assert env.physics.data.time == 0.0
  rng = np.random.default_rng(6)
  starts = 1
  while starts < 3:
    timestep = env.step(rng.uniform(-1, 1, 12))
    if timestep.first():
      starts += 1
      assert env.physics.data.time == 0.0
    else:
      assert env.physics.data.time > 0.0


# --- Terrain ------------------------------------------------------------------


def test_only_random_dynamics_variants_have_a_heightfield(dkitty_task_id):
  env = suite.load(*dkitty_task_id, seed=0)
  has_terrain = dkitty_task_id in suite.RANDOM_DYNAMICS
  assert env.physics.model.nhfield == int(has_terrain)
  assert env.task.arena.has_terrain == has_terrain


def test_terrain_is_redrawn_every_episode_without_recompiling():
  env = suite.load('dkitty', 'walk_random_dynamics', seed=0)
  physics = env.physics  # A weak proxy: dead if the model were recompiled.
  model = physics.model.ptr
  heights = []
  for _ in range(4):
    env.reset()
    data = physics.model.hfield_data.copy()
    assert data.size == 120 * 120
    assert data.min() >= 0.0 and data.max() <= 0.05
    assert data.max() > 0.045 and data.min() < 0.005
    assert len(np.unique(data)) > 0.9 * data.size  # I.i.d. per cell.
    np.testing.assert_array_equal(env.task.arena.terrain_heights, data)
    heights.append(data)
    env.step(_standing_action(env))
    # Regenerating never creates a rendering context by itself.
    assert env.physics._contexts is None
  assert physics.model.ptr is model and env.physics.model.ptr is model
  for first, second in zip(heights, heights[1:], strict=False):
    assert np.all(first != second)


def test_terrain_reaches_an_existing_renderer(monkeypatch):
  env = suite.load('dkitty', 'walk_random_dynamics', seed=0)
  env.reset()
  assert env.physics.render(64, 64).shape == (64, 64, 3)
  assert env.physics._contexts is not None
  uploads = []
  upload = mujoco.mjr_uploadHField

  def record(model, context, hfield_id):
    uploads.append(hfield_id)
    return upload(model, context, hfield_id)

  monkeypatch.setattr(mujoco, 'mjr_uploadHField', record)
  before = env.physics.model.hfield_data.copy()
  assert env.reset().first()
  assert uploads == [0]  # The only heightfield, once per reset.
  assert np.all(env.physics.model.hfield_data != before)
  assert env.physics.render(64, 64).shape == (64, 64, 3)
  assert env.step(_standing_action(env)).mid()
  env.reset()
  assert uploads == [0, 0]
  env.close()


# --- Standing -----------------------------------------------------------------


def _stand_for_five_seconds(env):
  """Commands the standing pose for 50 steps; returns the torso heights."""
  timestep = env.reset()
  assert timestep.first()
  action = _standing_action(env)
  heights = []
  for _ in range(50):
    timestep = env.step(action)
    assert timestep.mid() and timestep.discount == 1.0
    assert float(timestep.observation['upright'][0]) > 0.95
    heights.append(_torso(env).xpos[2])
  np.testing.assert_array_equal(env.physics.data.warning.number, 0)
  return np.array(heights)


@pytest.mark.parametrize('family', ['orient', 'walk'])
def test_robot_stands_still_on_flat_ground(family, kitty_envs):
  heights = _stand_for_five_seconds(kitty_envs[family])
  # ROBEL's compiled standing height is 0.302 m.
  np.testing.assert_allclose(heights, 0.30, atol=0.005)
  obs = kitty_envs[family].step(_standing_action(kitty_envs[family]))
  np.testing.assert_allclose(obs.observation['root_pos'], 0.0, atol=0.005)
  np.testing.assert_allclose(obs.observation['kitty_qpos'], 0.0, atol=0.02)


@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_robot_stands_on_random_terrain(seed):
  env = suite.load('dkitty', 'walk_random_dynamics', seed=seed)
  heights = _stand_for_five_seconds(env)
  # On bumps of up to 4.5 cm.
  assert np.all((heights > 0.29) & (heights < 0.36))
