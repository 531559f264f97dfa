"""Hand-built D'Kitty states and ROBEL's expected rewards, shared by the
D'Kitty task tests (computed from docs/robel_reference.md, independently of
robel_dm's tasks)."""

import math

from dm_control import mjcf
import mujoco
import numpy as np
import pytest

ORIGIN = np.array([0.0, 0.0, 0.3])  # ROBEL's kitty_frame start.
STANDING = np.zeros(12)
CROUCH = np.tile([0.0, np.pi / 4, -np.pi / 2], 4)  # ROBEL's StandFixed.
# Falling: upright threshold and falling term per family
# (docs/robel_reference.md section 2.4).
FALLING = {'stand': (0.0, -100.0), 'orient': (0.9, -500.0),
            'walk': (0.9, -500.0)}  # fmt: skip


# --- Rotations, independent of robel_dm ---------------------------------------


def rot_x(angle):
  c, s = math.cos(angle), math.sin(angle)
  return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(angle):
  c, s = math.cos(angle), math.sin(angle)
  return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(angle):
  c, s = math.cos(angle), math.sin(angle)
  return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


TILTS = {'x': rot_x, 'y': rot_y}


def pose(yaw=0.0, tilt_axis='x', tilt=0.0):
  """Torso-to-world rotation: turned by `yaw`, then tilted about its own
  x (pitch) or y (roll) axis."""
  return rot_z(yaw) @ TILTS[tilt_axis](tilt)


def quaternion(rotation):
  quat = np.zeros(4)
  mujoco.mju_mat2Quat(quat, np.asarray(rotation, float).ravel())
  return quat


def wrap(angle):
  return float(np.angle(np.exp(1j * angle)))


# --- Environment access -------------------------------------------------------


def root_joint(env):
  """The D'Kitty's free joint, bound to the physics."""
  return env.physics.bind(mjcf.get_frame_freejoint(env.task.robot.mjcf_model))


def leg_joints(env):
  return env.physics.bind(env.task.robot.joints)


def torso_body(env):
  return env.physics.bind(env.task.robot.torso)


def signal(env, name):
  """The current value of a task observable (also disabled ones)."""
  return np.array(env.task.task_observables[name](env.physics))


def set_state(env, position, rotation=None, legs=STANDING, qvel=None):
  """Writes a hand-built state and recomputes the task's signals from it.

  Args:
    env: a D'Kitty environment, reset.
    position: torso position in the world, m.
    rotation: torso-to-world rotation; level, facing +y if None.
    legs: the 12 leg joint angles, rad.
    qvel: the free joint's 6 velocities (MuJoCo's convention); zero if None.
  """
  rotation = np.eye(3) if rotation is None else rotation
  root = root_joint(env)
  root.qpos = np.concatenate([position, quaternion(rotation)])
  root.qvel = np.zeros(6) if qvel is None else qvel
  leg_joints(env).qpos = legs
  leg_joints(env).qvel = np.zeros(12)
  env.physics.forward()
  env.task._update(env.physics, env.random_state)


def hold(env):
  """The action that commands the legs' current angles."""
  return env.task.normalize_joint_targets(leg_joints(env).qpos.copy())


def standing_action(env):
  return env.task.normalize_joint_targets(STANDING)


def stand_expected(upright, legs, xy):
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


def orient_expected(upright, angle_error, xy):
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


def walk_expected(upright, heading, distance):
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


def assert_signals(env, terms, points, upright, threshold):
  """Compares the task's uprightness, terms, reward, score, success and
  failure with the expected ones."""
  assert float(signal(env, 'upright')[0]) == pytest.approx(upright, abs=1e-12)
  assert tuple(env.task.reward_terms) == tuple(terms)
  for name, value in terms.items():
    assert env.task.reward_terms[name] == pytest.approx(value, abs=1e-9), name
  reward = env.task.get_reward(env.physics)
  assert reward == pytest.approx(sum(terms.values()), abs=1e-9)
  assert float(signal(env, 'score')) == pytest.approx(points, abs=1e-9)
  assert bool(signal(env, 'success')) == (terms['bonus_big'] > 0)
  fallen = upright < threshold
  assert env.task._failed == fallen
  assert env.task.should_terminate_episode(env.physics) == fallen
  assert env.task.get_discount(env.physics) == (0.0 if fallen else 1.0)


# Stand states: torso xy, yaw, tilt axis and angle, mean |joint error| of
# legs with mixed signs.
