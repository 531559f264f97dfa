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

from kitty_states import (
  FALLING,
  ORIGIN,
  assert_signals,
  leg_joints,
  orient_expected,
  pose,
  root_joint,
  rot_x,
  rot_y,
  rot_z,
  set_state,
  signal,
  stand_expected,
  torso_body,
  walk_expected,
  wrap,
)
import mujoco
import numpy as np
import pytest
import robel_spec

from robel_dm import geometry, suite

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


@pytest.mark.slow
def test_stand_terms_on_hand_built_states(kitty_envs):
  env = kitty_envs['stand']
  env.reset()
  signs = np.resize([1.0, -1.0, -1.0], 12)
  for xy, yaw, axis, tilt, error in _STAND_STATES:
    legs = error * signs
    position = np.array([*xy, 0.3])
    set_state(env, position, pose(yaw, axis, tilt), legs)
    upright = math.cos(tilt)
    terms, points = stand_expected(upright, legs, xy)
    assert_signals(env, terms, points, upright, threshold=0.0)
    np.testing.assert_allclose(signal(env, 'pose_error'), -legs, atol=1e-12)
  # The test's own data covers every bonus combination, the points'
  # saturation and a fall.
  cases = []
  for xy, _, _, tilt, error in _STAND_STATES:
    terms, points = stand_expected(math.cos(tilt), error * signs, xy)
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
    set_state(env, [*xy, 0.25], pose(rng.uniform(-3, 3), 'y', tilt), legs)
    upright = math.cos(tilt)
    terms, points = stand_expected(upright, legs, xy)
    assert_signals(env, terms, points, upright, threshold=0.0)


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
    set_state(env, [*xy, 0.3], pose(yaw, axis, tilt))
    upright = math.cos(tilt)
    to_target = target - xy
    desired = math.atan2(to_target[1], to_target[0])
    angle_error = abs(wrap(desired - (yaw + np.pi / 2)))
    terms, points = orient_expected(upright, angle_error, xy)
    assert_signals(env, terms, points, upright, threshold=0.9)
    facing = pose(yaw, axis, tilt)[:2, 1]
    np.testing.assert_allclose(signal(env, 'current_facing'), facing,
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(
      signal(env, 'desired_facing'),
      to_target / np.linalg.norm(to_target),
      atol=1e-12,
    )
    assert float(signal(env, 'angle_error')[0]) == pytest.approx(
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
    set_state(env, [*xy, 0.3], pose(yaw, axis, tilt))
    upright = math.cos(tilt)
    error = target - xy
    heading = math.cos(math.atan2(error[1], error[0]) - (yaw + np.pi / 2))
    terms, points = walk_expected(upright, heading, np.linalg.norm(error))
    assert_signals(env, terms, points, upright, threshold=0.9)
    assert float(signal(env, 'heading')[0]) == pytest.approx(heading)
    np.testing.assert_allclose(signal(env, 'target_error'), error, atol=1e-12)
    np.testing.assert_allclose(signal(env, 'target_pos'), target, atol=1e-12)


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
    set_state(env, [0.0, 0.0, 0.3], pose(np.pi + offset, 'y', tilt))
    assert float(signal(env, 'angle_error')[0]) == pytest.approx(offset)
    terms = env.task.reward_terms
    assert (terms['bonus_small'], terms['bonus_big']) == (small, big)


def test_walk_small_bonus_is_a_logical_or(kitty_envs):
  env = kitty_envs['walk']
  env.reset()
  for xy, yaw, small, big in _WALK_BONUSES:
    set_state(env, [*xy, 0.3], pose(yaw))
    terms = env.task.reward_terms
    assert (terms['bonus_small'], terms['bonus_big']) == (small, big)


def _expected_from_physics(env, family):
  """ROBEL's terms and points of the current (true) physics state."""
  torso = torso_body(env)
  upright, xy = float(torso.xmat[8]), torso.xpos[:2].copy()
  facing = torso.xmat[[1, 4]]  # The torso's y axis on the floor.
  if family == 'stand':
    return stand_expected(upright, leg_joints(env).qpos.copy(), xy)
  to_target = env.task.target - xy
  cosine = np.dot(facing, to_target) / (
    np.linalg.norm(facing) * np.linalg.norm(to_target)
  )
  if family == 'orient':
    return orient_expected(upright, math.acos(np.clip(cosine, -1, 1)), xy)
  return walk_expected(upright, cosine, np.linalg.norm(to_target))


@pytest.mark.slow
def test_reward_is_the_sum_of_robels_terms_on_real_steps(dkitty_task_id):
  env = suite.load(*dkitty_task_id, seed=0)
  family = robel_spec.family(dkitty_task_id)
  threshold, _ = FALLING[family]
  timestep = env.reset()
  policy = robel_spec.steady_policy(env, seed=4, noise=0.3)
  for _ in range(12):
    timestep = env.step(policy(timestep))
    terms, points = _expected_from_physics(env, family)
    upright = float(torso_body(env).xmat[8])
    assert_signals(env, terms, points, upright, threshold)
    assert timestep.reward == pytest.approx(sum(terms.values()), abs=1e-9)
    assert float(timestep.observation['score']) == pytest.approx(points)
    if timestep.last():
      break


# --- Torso observations -------------------------------------------------------


@pytest.mark.parametrize(
  'rotation, upright',
  [
    (np.eye(3), 1.0),
    (rot_x(np.pi), -1.0),
    (rot_y(np.pi), -1.0),
    (rot_x(np.pi / 6), math.cos(np.pi / 6)),
    (rot_y(-0.9), math.cos(0.9)),
    (rot_z(1.0) @ rot_x(2.0), math.cos(2.0)),
    (rot_z(-2.5) @ rot_y(0.3) @ rot_x(0.4), math.cos(0.3) * math.cos(0.4)),
  ],
  ids=['level', 'flipped_x', 'flipped_y', 'tilt_30', 'roll_0.9', 'tilt_2',
       'tilt_both'],
)  # fmt: skip
def test_upright_is_the_cosine_of_the_tilt(rotation, upright, kitty_envs):
  for env in kitty_envs.values():
    env.reset()
    set_state(env, ORIGIN, rotation)
    assert float(signal(env, 'upright')[0]) == pytest.approx(upright, abs=1e-12)


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
    set_state(env, ORIGIN, rot_z(yaw))
    np.testing.assert_allclose(signal(env, 'root_euler'), [0.0, 0.0, yaw],
                               atol=1e-12)  # fmt: skip
  # Orient's target is at (0, -1): heading -pi/2 from the origin.
  np.testing.assert_allclose(signal(orient, 'current_facing'), facing,
                             atol=1e-12)  # fmt: skip
  np.testing.assert_allclose(signal(orient, 'desired_facing'), [0, -1],
                             atol=1e-12)  # fmt: skip
  angle_error = abs(wrap(-np.pi / 2 - (yaw + np.pi / 2)))
  assert float(signal(orient, 'angle_error')[0]) == pytest.approx(angle_error)
  # Walk's target is at (0, 2): straight ahead at yaw 0.
  heading = float(signal(walk, 'heading')[0])
  assert heading == pytest.approx(math.cos(yaw), abs=1e-12)
  assert heading == pytest.approx(facing[1], abs=1e-12)


def test_root_position_is_relative_to_robels_frame_origin(kitty_envs):
  for env in kitty_envs.values():
    env.reset()
    set_state(env, [0.2, -0.1, 0.45])
    np.testing.assert_allclose(
      signal(env, 'root_pos'), [0.2, -0.1, 0.15], atol=1e-12
    )
    np.testing.assert_allclose(torso_body(env).xpos, [0.2, -0.1, 0.45])


def test_root_euler_is_robels_rotating_xyz(kitty_envs):
  env = kitty_envs['walk']
  env.reset()
  rng = np.random.default_rng(1)
  for _ in range(10):
    a, c = rng.uniform(-np.pi, np.pi, 2)
    b = rng.uniform(-1.5, 1.5)
    set_state(env, ORIGIN, rot_x(a) @ rot_y(b) @ rot_z(c))
    np.testing.assert_allclose(signal(env, 'root_euler'), [a, b, c],
                               atol=1e-9)  # fmt: skip


def test_euler_xyz_inverts_rx_ry_rz():
  rng = np.random.default_rng(2)
  for _ in range(200):
    a, c = rng.uniform(-np.pi, np.pi, 2)
    b = rng.uniform(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3)
    rotation = rot_x(a) @ rot_y(b) @ rot_z(c)
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
    start = rot_x(a) @ rot_y(b) @ rot_z(c)
    omega = rng.uniform(-3, 3, 3)
    after = np.array(geometry.euler_xyz(_rotation_exp(omega, h) @ start))
    before = np.array(geometry.euler_xyz(_rotation_exp(omega, -h) @ start))
    expected = [wrap(d) / (2 * h) for d in after - before]
    rates = geometry.euler_xyz_rates((a, b, c), omega)
    np.testing.assert_allclose(rates, expected, rtol=1e-6, atol=1e-6)


def _integrated_pose(env, qpos, qvel, dt):
  """Free-joint position and rotation after moving at `qvel` for `dt`
  (MuJoCo's own integration, whatever its velocity convention)."""
  moved = qpos.copy()
  mujoco.mj_integratePos(env.physics.model.ptr, moved, qvel, dt)
  root = root_joint(env)
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
    set_state(
      env, [0.1, 0.2, 0.3], rot_x(a) @ rot_y(b) @ rot_z(c), qvel=root_qvel
    )
    qpos, qvel = env.physics.data.qpos.copy(), env.physics.data.qvel.copy()
    position_after, after = _integrated_pose(env, qpos, qvel, h)
    position_before, before = _integrated_pose(env, qpos, qvel, -h)
    velocity = (position_after - position_before) / (2 * h)
    rates = [
      wrap(d) / (2 * h)
      for d in np.subtract(
        geometry.euler_xyz(after), geometry.euler_xyz(before)
      )
    ]
    np.testing.assert_allclose(signal(env, 'root_vel'), velocity, atol=1e-6)
    np.testing.assert_allclose(
      signal(env, 'root_angular_vel'), rates, rtol=1e-5, atol=1e-5
    )


# --- Falling ------------------------------------------------------------------
