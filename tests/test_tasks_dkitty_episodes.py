"""D'Kitty tasks' episodes against ROBEL's: falling and discounts, initial
states and goals of every variant, the terrain, and that the robot stands
(see test_tasks_dkitty.py for the rewards and the torso's frames)."""

import math

from kitty_states import (
  CROUCH,
  FALLING,
  ORIGIN,
  STANDING,
  hold,
  leg_joints,
  root_joint,
  rot_x,
  rot_y,
  set_state,
  signal,
  standing_action,
  torso_body,
)
import mujoco
import numpy as np
import pytest
import robel_spec

from robel_dm import suite


@pytest.mark.slow
@pytest.mark.parametrize(
  'family, rotation, falls',
  [
    ('stand', rot_x(np.pi), True),
    ('stand', rot_y(np.pi), True),
    ('stand', rot_x(np.pi / 3), False),  # Stand falls at 90 degrees only.
    ('orient', rot_x(np.pi / 3), True),
    ('orient', rot_y(np.pi), True),
    ('walk', rot_y(np.pi / 3), True),
    ('walk', rot_x(np.pi), True),
  ],
  ids=['stand-flipped_x', 'stand-flipped_y', 'stand-tilt_60',
       'orient-tilt_60', 'orient-flipped_y', 'walk-roll_60',
       'walk-flipped_x'],
)  # fmt: skip
def test_falling_ends_the_episode_with_discount_zero(
  family, rotation, falls, kitty_envs
):
  env = kitty_envs[family]
  threshold, falling = FALLING[family]
  timestep = env.reset()
  for _ in range(3):
    timestep = env.step(hold(env))
    assert timestep.mid() and timestep.discount == 1.0
  # Tip the robot over (where it stands), then take a step.
  set_state(
    env, torso_body(env).xpos.copy(), rotation, leg_joints(env).qpos.copy()
  )
  timestep = env.step(hold(env))
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
  timestep = env.step(hold(env))
  assert timestep.first()
  assert timestep.reward is None and timestep.discount is None
  assert env.physics.data.time == 0.0
  assert float(timestep.observation['upright'][0]) > 0.99
  assert env.step(hold(env)).mid()


@pytest.mark.slow
def test_discount_is_zero_exactly_when_the_robot_has_fallen(dkitty_task_id):
  # Random bang-bang actions topple the D'Kitty in about half the episodes
  # (or more); only a fall gives discount 0.
  env = suite.load(*dkitty_task_id, seed=1)
  threshold, falling = FALLING[robel_spec.family(dkitty_task_id)]
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
    np.testing.assert_allclose(leg_joints(env).qpos, CROUCH, atol=0.03)
    np.testing.assert_allclose(obs['kitty_qpos'], leg_joints(env).qpos)
    # ROBEL's compiled crouch settles at a torso height of 0.244 m.
    assert torso_body(env).xpos[2] == pytest.approx(0.244, abs=0.005)
    assert obs['root_pos'][2] == pytest.approx(0.244 - 0.3, abs=0.005)
    np.testing.assert_allclose(obs['root_pos'][:2], 0.0, atol=0.01)
    assert obs['upright'][0] > 0.999
    # It has settled: it barely moves any more.
    assert np.abs(obs['root_vel']).max() < 0.01
    assert np.abs(obs['kitty_qvel']).max() < 0.1
    np.testing.assert_array_equal(obs['last_action'], 0.0)
    for _ in range(3):
      env.step(hold(env))


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
    assert np.abs(leg_joints(env).qpos - pose).max() < 0.5
    assert torso_body(env).xpos[2] < 0.3  # Settled onto the floor.
    poses.append(pose)
  poses = np.array(poses)
  # Every joint spreads over its action range.
  assert np.all((poses.max(0) - poses.min(0)) > 0.5 * (high - low))


@pytest.mark.slow
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
    np.testing.assert_array_equal(leg_joints(drawn).qpos, pose)
    np.testing.assert_array_equal(leg_joints(drawn).qvel, 0.0)
    np.testing.assert_array_equal(torso_body(drawn).xpos, ORIGIN)
    np.testing.assert_array_equal(root_joint(drawn).qvel, 0.0)
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
    np.testing.assert_array_equal(obs['kitty_qpos'], STANDING)
    np.testing.assert_array_equal(obs['kitty_qvel'], 0.0)
    np.testing.assert_array_equal(obs['root_vel'], 0.0)
    assert float(signal(env, 'angle_error')[0]) == pytest.approx(np.pi)
    _assert_marker(env, 'target', [0.0, -1.0])
    env.step(standing_action(env))


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
    np.testing.assert_array_equal(obs['kitty_qpos'], STANDING)
    _assert_marker(env, 'target', [0.0, 2.0])
    _assert_marker(env, 'heading', [0.0, 2.0])
    env.step(standing_action(env))


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


@pytest.mark.slow
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


@pytest.mark.slow
def test_only_random_dynamics_variants_have_a_heightfield(dkitty_task_id):
  env = suite.load(*dkitty_task_id, seed=0)
  has_terrain = dkitty_task_id in suite.RANDOM_DYNAMICS
  assert env.physics.model.nhfield == int(has_terrain)
  assert env.task.arena.has_terrain == has_terrain


@pytest.mark.slow
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
    env.step(standing_action(env))
    # Regenerating never creates a rendering context by itself.
    assert env.physics._contexts is None
  assert physics.model.ptr is model and env.physics.model.ptr is model
  for first, second in zip(heights, heights[1:], strict=False):
    assert np.all(first != second)


@pytest.mark.slow
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
  assert env.step(standing_action(env)).mid()
  env.reset()
  assert uploads == [0, 0]
  env.close()


# --- Standing -----------------------------------------------------------------


def _stand_for_five_seconds(env):
  """Commands the standing pose for 50 steps; returns the torso heights."""
  timestep = env.reset()
  assert timestep.first()
  action = standing_action(env)
  heights = []
  for _ in range(50):
    timestep = env.step(action)
    assert timestep.mid() and timestep.discount == 1.0
    assert float(timestep.observation['upright'][0]) > 0.95
    heights.append(torso_body(env).xpos[2])
  np.testing.assert_array_equal(env.physics.data.warning.number, 0)
  return np.array(heights)


@pytest.mark.parametrize('family', ['orient', 'walk'])
def test_robot_stands_still_on_flat_ground(family, kitty_envs):
  heights = _stand_for_five_seconds(kitty_envs[family])
  # ROBEL's compiled standing height is 0.302 m.
  np.testing.assert_allclose(heights, 0.30, atol=0.005)
  obs = kitty_envs[family].step(standing_action(kitty_envs[family]))
  np.testing.assert_allclose(obs.observation['root_pos'], 0.0, atol=0.005)
  np.testing.assert_allclose(obs.observation['kitty_qpos'], 0.0, atol=0.02)


@pytest.mark.slow
@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_robot_stands_on_random_terrain(seed):
  env = suite.load('dkitty', 'walk_random_dynamics', seed=seed)
  heights = _stand_for_five_seconds(env)
  # On bumps of up to 4.5 cm.
  assert np.all((heights > 0.29) & (heights < 0.36))
