"""Tests of the composer entities: the D'Claw, the valves and the station;
the D'Kitty and its floor."""

from dm_control import mjcf
import numpy as np
import pytest
import robel_spec

from robel_dm import suite
from robel_dm.arenas import floor, station
from robel_dm.entities import dclaw, dkitty, valve

# ROBEL's joint (= action) order: finger FF, MF, TH; top, middle, bottom.
_ROBEL_JOINT_ORDER = (
  'FFJ10', 'FFJ11', 'FFJ12',
  'MFJ20', 'MFJ21', 'MFJ22',
  'THJ30', 'THJ31', 'THJ32',
)  # fmt: skip
_HALF_RANGE = np.tile([0.48, np.pi / 3, np.pi / 2], 3)


def test_dclaw_joints_and_actuators_are_in_robels_order():
  claw = dclaw.DClaw()
  assert tuple(j.name for j in claw.joints) == _ROBEL_JOINT_ORDER
  assert len(claw.actuators) == 9
  for joint, actuator in zip(claw.joints, claw.actuators, strict=True):
    assert actuator.joint is joint  # Each actuator drives its own joint.
    assert actuator.tag == 'position'
  physics = mjcf.Physics.from_mjcf_model(claw.mjcf_model)
  ctrlrange = physics.bind(claw.actuators).ctrlrange
  np.testing.assert_allclose(
    ctrlrange, np.stack([-_HALF_RANGE, _HALF_RANGE], 1)
  )
  # The compiled model keeps the order: actuator i drives joint i.
  joint_ids = physics.bind(claw.joints).element_id
  np.testing.assert_array_equal(
    physics.model.actuator_trnid[physics.bind(claw.actuators).element_id, 0],
    joint_ids,
  )
  assert len(claw.fingertip_sites) == 3


def test_dclaw_observables_are_keyed_by_model_name_and_evaluate():
  env = suite.load('dclaw', 'pose_fixed', seed=0)
  env.reset()
  claw, physics = env.task.robot, env.physics
  observables = env.task.observables
  assert {'dclaw/joints_pos', 'dclaw/joints_vel', 'dclaw/fingertips_pos'} <= (
    set(observables)
  )
  joints = physics.bind(claw.joints)
  joints.qpos = np.linspace(-0.4, 0.4, 9)
  joints.qvel = np.linspace(1.0, 2.0, 9)
  physics.forward()
  np.testing.assert_array_equal(
    observables['dclaw/joints_pos'](physics), joints.qpos
  )
  np.testing.assert_array_equal(
    observables['dclaw/joints_vel'](physics), joints.qvel
  )
  tips = observables['dclaw/fingertips_pos'](physics)
  np.testing.assert_array_equal(tips, physics.bind(claw.fingertip_sites).xpos)
  assert tips.shape == (3, 3)


def test_enabled_entity_observables_reach_the_timestep():
  env = suite.load('dclaw', 'turn_fixed', seed=0)
  claw, prop = env.task.robot, env.task.valve
  claw.observables.joints_pos.enabled = True
  prop.observables.angle.enabled = True
  env.reset()
  timestep = env.step(np.full(9, 0.1))
  obs = timestep.observation
  np.testing.assert_array_equal(
    obs['dclaw/joints_pos'], env.physics.bind(claw.joints).qpos
  )
  np.testing.assert_array_equal(
    obs['valve/angle'], env.physics.bind(prop.hinge).qpos
  )
  # The agent's keys are still the default ones.
  assert 'dclaw/joints_pos' not in env.task.agent_observation_keys


def test_valve_variants():
  assert set(valve.VARIANTS) == {'valve3', 'valve4'}
  for variant in valve.VARIANTS:
    prop = valve.Valve(variant=variant)
    assert prop.variant == variant
    assert prop.mjcf_model.model == 'valve'  # Same keys for both variants.
    assert prop.hinge.limited in (None, False, 'false')
    physics = mjcf.Physics.from_mjcf_model(prop.mjcf_model)
    hinge = physics.bind(prop.hinge)
    assert not physics.model.jnt_limited[hinge.element_id]
    geoms = physics.bind(prop.valve_geoms).element_id
    capsules = physics.model.geom_type[geoms] == 3  # mjGEOM_CAPSULE
    assert capsules.sum() == {'valve3': 3, 'valve4': 2}[variant]
    body = physics.bind(prop.valve_body).element_id
    np.testing.assert_array_equal(
      np.sort(geoms), np.flatnonzero(physics.model.geom_bodyid == body)
    )


@pytest.mark.parametrize('bad', ['valve5', 'Valve3', ''])
def test_valve_rejects_unknown_variants(bad):
  with pytest.raises(ValueError, match=f'unknown valve {bad!r}'):
    valve.Valve(variant=bad)


def test_station_mount_heights_are_robels():
  for height, expected in ((station.MOUNT_HEIGHT_POSE, 0.30),
                           (station.MOUNT_HEIGHT_VALVE, 0.335)):  # fmt: skip
    assert height == expected
    arena = station.ClawStation(mount_height=height)
    physics = mjcf.Physics.from_mjcf_model(arena.mjcf_model)
    np.testing.assert_allclose(physics.bind(arena.mount).xpos, [0, 0, height])


@pytest.mark.slow
def test_tasks_mount_the_claw_at_robels_heights(
  dclaw_nominal_task_id, shared_env
):
  task_id = dclaw_nominal_task_id  # RandomDynamics moves the mount.
  env = shared_env(task_id)
  env.reset()
  expected = 0.30 if task_id[1].startswith('pose') else 0.335
  mount = env.physics.bind(env.task.arena.mount).xpos
  np.testing.assert_allclose(mount, [0, 0, expected])


@pytest.mark.slow
def test_pose_fixed_is_truly_fixed():
  envs = [suite.load('dclaw', 'pose_fixed', seed=seed) for seed in (0, 1)]
  first = [env.reset() for env in envs]
  goals = [env.task.goal for env in envs]
  np.testing.assert_array_equal(goals[0], goals[1])
  for key in first[0].observation:
    np.testing.assert_array_equal(
      first[0].observation[key], first[1].observation[key]
    )
  # And again after an episode's worth of steps with different actions.
  rng = np.random.default_rng(0)
  for env in envs:
    for _ in range(10):
      env.step(rng.uniform(-1, 1, 9))
  again = [env.reset() for env in envs]
  for key in first[0].observation:
    np.testing.assert_array_equal(
      again[0].observation[key], first[0].observation[key]
    )
    np.testing.assert_array_equal(
      again[1].observation[key], first[0].observation[key]
    )
  np.testing.assert_array_equal(envs[0].task.goal, goals[0])
  np.testing.assert_array_equal(envs[1].task.goal, goals[0])
  # The fixed goal differs from the fixed initial pose.
  assert np.abs(first[0].observation['qpos_error']).mean() > 0.1


# --- The D'Kitty --------------------------------------------------------------

# ROBEL's joint (= action) order: legs FR, FL, BL, BR; hip, upper leg, knee.
_KITTY_JOINT_ORDER = (
  'FRJ10', 'FRJ11', 'FRJ12',
  'FLJ20', 'FLJ21', 'FLJ22',
  'BLJ30', 'BLJ31', 'BLJ32',
  'BRJ40', 'BRJ41', 'BRJ42',
)  # fmt: skip


@pytest.mark.slow
def test_dkitty_joints_and_actuators_are_in_robels_order():
  kitty = dkitty.DKitty()
  assert tuple(j.name for j in kitty.joints) == _KITTY_JOINT_ORDER
  assert len(kitty.actuators) == 12
  for joint, actuator in zip(kitty.joints, kitty.actuators, strict=True):
    assert actuator.joint is joint
    assert actuator.tag == 'position'
  physics = mjcf.Physics.from_mjcf_model(kitty.mjcf_model)
  ctrlrange = physics.bind(kitty.actuators).ctrlrange
  np.testing.assert_allclose(
    ctrlrange,
    np.stack([robel_spec.DKITTY_ACTION_LOW, robel_spec.DKITTY_ACTION_HIGH], 1),
    rtol=0,
    atol=1e-12,
  )
  joint_ids = physics.bind(kitty.joints).element_id
  np.testing.assert_array_equal(
    physics.model.actuator_trnid[physics.bind(kitty.actuators).element_id, 0],
    joint_ids,
  )
  assert [site.name for site in kitty.foot_sites] == [
    'FRfoot', 'FLfoot', 'BLfoot', 'BRfoot'
  ]  # fmt: skip
  assert kitty.max_joint_speed == np.pi
  assert kitty.safety_limits.position_range == 'joint'
  assert dclaw.DClaw().safety_limits.position_range == 'action'


def test_dkitty_poses_are_robels():
  np.testing.assert_array_equal(dkitty.STANDING_POSE, np.zeros(12))
  np.testing.assert_allclose(
    dkitty.CROUCHED_POSE, np.tile([0.0, np.pi / 4, -np.pi / 2], 4)
  )
  np.testing.assert_array_equal(dkitty.ROBEL_FRAME_ORIGIN, [0.0, 0.0, 0.3])


@pytest.mark.slow
@pytest.mark.parametrize('task', ['stand_fixed', 'orient_random', 'walk_fixed'])
def test_foot_sites_are_on_their_legs_in_the_compiled_task(task, shared_env):
  # The robot faces +y and its right side is +x (ROBEL swapped the FR and
  # FL site names; robel_dm names each foot after its leg).
  env = shared_env(('dkitty', task))
  env.reset()
  kitty, physics = env.task.robot, env.physics
  feet = physics.bind(kitty.foot_sites).xpos
  # In the torso's frame (Orient turns the robot).
  torso = physics.bind(kitty.torso)
  local = (feet - torso.xpos) @ torso.xmat.reshape(3, 3)
  for site, (x, y, _) in zip(kitty.foot_sites, local, strict=True):
    right, front = site.name[1] == 'R', site.name[0] == 'F'
    assert (x > 0.05) == right and (x < -0.05) == (not right), site.name
    assert (y > 0.1) == front and (y < -0.1) == (not front), site.name
    assert site.parent.name == f'{site.name[:2]}{_leg_number(site)}2'
  # Before any turn, world and torso axes agree.
  if task != 'orient_random':
    np.testing.assert_array_equal(
      np.sign(feet[:, :2]), [[1, 1], [-1, 1], [-1, -1], [1, -1]]
    )
  # The feet stand on the floor.
  np.testing.assert_array_less(feet[:, 2], 0.03)


def _leg_number(site):
  return {'FR': 1, 'FL': 2, 'BL': 3, 'BR': 4}[site.name[:2]]


def test_dkitty_observables_are_keyed_by_model_name_and_evaluate():
  env = suite.load('dkitty', 'walk_fixed', seed=0)
  env.reset()
  kitty, physics = env.task.robot, env.physics
  observables = env.task.observables
  names = ('joints_pos', 'joints_vel', 'torso_pos', 'torso_xmat', 'feet_pos')
  assert {f'dkitty/{name}' for name in names} <= set(observables)
  joints = physics.bind(kitty.joints)
  joints.qpos = np.linspace(-0.4, 0.4, 12)
  joints.qvel = np.linspace(1.0, 2.0, 12)
  physics.forward()
  np.testing.assert_array_equal(
    observables['dkitty/joints_pos'](physics), joints.qpos
  )
  np.testing.assert_array_equal(
    observables['dkitty/joints_vel'](physics), joints.qvel
  )
  torso = physics.bind(kitty.torso)
  np.testing.assert_array_equal(
    observables['dkitty/torso_pos'](physics), torso.xpos
  )
  np.testing.assert_array_equal(
    observables['dkitty/torso_xmat'](physics), torso.xmat
  )
  feet = observables['dkitty/feet_pos'](physics)
  assert feet.shape == (4, 3)
  np.testing.assert_array_equal(feet, physics.bind(kitty.foot_sites).xpos)


def test_kitty_floor_has_a_heightfield_only_with_terrain():
  for terrain in (False, True):
    arena = floor.KittyFloor(terrain=terrain)
    assert arena.has_terrain == terrain
    physics = mjcf.Physics.from_mjcf_model(arena.mjcf_model)
    assert physics.model.nhfield == int(terrain)
    assert physics.model.ngeom == 1 + terrain
    arena.after_compile(physics, np.random.RandomState(0))
    heights = arena.terrain_heights
    if not terrain:
      assert heights is None
      arena.regenerate(physics, np.random.RandomState(0))  # A no-op.
      continue
    assert heights.shape == (120 * 120,)
    np.testing.assert_array_equal(physics.model.hfield_size[0],
                                  [4.5, 4.5, 1.0, 0.1])  # fmt: skip
    np.testing.assert_array_equal(physics.model.hfield_nrow, [120])
    np.testing.assert_array_equal(physics.model.hfield_ncol, [120])
    arena.regenerate(physics, np.random.RandomState(0))
    # The heights are the model's (a view), ROBEL's U(0, 0.05) m.
    np.testing.assert_array_equal(physics.model.hfield_data, heights)
    assert heights.min() >= 0.0 and heights.max() <= 0.05
    assert heights.max() > 0.049 and heights.min() < 0.001
