"""Tests of dynamics randomization and observation noise.

The ranges below are ROBEL's, written out from docs/robel_reference.md
(sections 2 and 6); the nominal model is the compiled model of the task
family's Fixed variant.
"""

import dataclasses

from dm_control import mjcf
import mujoco
import numpy as np
import pytest
import robel_spec

from robel_dm import randomization, suite
from robel_dm.entities import dclaw

_RESETS = 30

# ROBEL's RandomDynamics ranges (docs/robel_reference.md sections 2.1, 2.2).
_DAMPING = (0.005, 0.1)
_FRICTION_LOSS = (0.001, 0.005)
_KP = (1.0, 3.0)
_SLIDE = (0.8, 1.2)  # Absolute, for ROBEL's default (metal) friction.
_SPIN = (0.003, 0.007)
_ROLL = (5e-5, 1.5e-4)
_METAL_FRICTION = np.array([1.0, 0.005, 0.0001])
_MOUNT_OFFSET = 0.01
_COLOR = (0.2, 0.9)
_PLASTIC_RATIO = 0.2  # Plastic (fingertips, valve) to metal slide friction.

# The D'Kitty's (docs/robel_reference.md section 2.4): one damping and one
# friction-loss draw for all leg DOFs, kp per task, total mass.
_KITTY_DAMPING = (0.1, 0.2)
_KITTY_KP_STAND = (2.0, 4.0)
_KITTY_KP_WALK = (2.8, 3.2)  # Orient and Walk.
_KITTY_MASS = (1.6, 2.0)
_TERRAIN = (0.0, 0.05)

# Observation noise half-widths: 0.05 * range width / 2
# (docs/robel_reference.md section 6).
_CLAW_QPOS_NOISE = 0.05 * np.tile([0.96, 2 * np.pi / 3, np.pi], 3) / 2
_CLAW_QVEL_NOISE = 0.05 * (4 * np.pi / 3) / 2
_VALVE_NOISE = 0.05 * np.pi
# The D'Kitty's leg joints: hips 0.779, upper legs pi/2, knees 2.0 wide;
# velocities +-pi rad/s.
_KITTY_QPOS_NOISE = 0.05 * np.tile([0.779, np.pi / 2, 2.0], 4) / 2
_KITTY_QVEL_NOISE = 0.05 * (2 * np.pi) / 2

_MODEL_FIELDS = (
  'dof_damping',
  'dof_frictionloss',
  'actuator_gainprm',
  'actuator_biasprm',
  'geom_friction',
  'body_pos',
  'geom_rgba',
  'body_mass',
  'body_inertia',
)


def _family(task_id):
  return task_id[1].split('_')[0]


def _is_pose(task_id):
  return _family(task_id) == 'pose'


def _fixed_counterpart(task_id):
  (match,) = [t for t in suite.FIXED if _family(t) == _family(task_id)]
  return match


def _snapshot(model):
  return {name: getattr(model, name).copy() for name in _MODEL_FIELDS}


def _within(values, bounds, tolerance=1e-12):
  values = np.asarray(values)
  return bool(
    np.all(values >= bounds[0] - tolerance)
    and np.all(values <= bounds[1] + tolerance)
  )


# --- The range data ----------------------------------------------------------


def test_range_constants_are_robels():
  pose, valve = randomization.DCLAW_POSE, randomization.DCLAW_VALVE
  for ranges in (pose, valve):
    assert (ranges.damping.low, ranges.damping.high) == _DAMPING
    assert (ranges.friction_loss.low, ranges.friction_loss.high) == (
      _FRICTION_LOSS
    )
    assert (ranges.actuator_kp.low, ranges.actuator_kp.high) == _KP
    assert not ranges.damping_shared and not ranges.friction_loss_shared
    assert ranges.total_mass is None
  assert pose.geom_friction is None
  assert pose.mount_offset is None and pose.color is None
  friction = valve.geom_friction
  np.testing.assert_array_equal(friction.low, [_SLIDE[0], _SPIN[0], _ROLL[0]])
  np.testing.assert_array_equal(friction.high, [_SLIDE[1], _SPIN[1], _ROLL[1]])
  assert (valve.mount_offset.low, valve.mount_offset.high) == (-0.01, 0.01)
  assert (valve.color.low, valve.color.high) == _COLOR


def test_dkitty_range_constants_are_robels():
  stand, locomotion = (
    randomization.DKITTY_STAND,
    randomization.DKITTY_LOCOMOTION,
  )
  for ranges, kp in ((stand, _KITTY_KP_STAND), (locomotion, _KITTY_KP_WALK)):
    assert (ranges.damping.low, ranges.damping.high) == _KITTY_DAMPING
    assert (ranges.friction_loss.low, ranges.friction_loss.high) == (
      _FRICTION_LOSS
    )
    assert ranges.damping_shared and ranges.friction_loss_shared
    assert (ranges.actuator_kp.low, ranges.actuator_kp.high) == kp
    friction = ranges.geom_friction
    np.testing.assert_array_equal(friction.low, [_SLIDE[0], _SPIN[0], _ROLL[0]])
    np.testing.assert_array_equal(
      friction.high, [_SLIDE[1], _SPIN[1], _ROLL[1]]
    )
    assert (ranges.total_mass.low, ranges.total_mass.high) == _KITTY_MASS
    assert ranges.mount_offset is None and ranges.color is None


def test_range_rejects_empty_ranges_and_checks_membership():
  with pytest.raises(ValueError, match='empty range'):
    randomization.Range(1.0, 0.5)
  with pytest.raises(ValueError, match='empty range'):
    randomization.Range((0.0, 1.0), (1.0, 0.5))
  span = randomization.Range(0.0, 1.0)
  assert span.contains([0.0, 0.5, 1.0])
  assert not span.contains([0.5, 1.5])
  samples = span.sample(np.random.RandomState(0), 100)
  assert samples.shape == (100,) and span.contains(samples)


def test_noise_halfwidths_are_a_fraction_of_half_the_width():
  halfwidths = randomization.noise_halfwidths([2.0, 4.0], 0.05)
  np.testing.assert_allclose(halfwidths, [0.05, 0.1])


# --- RandomDynamics tasks ----------------------------------------------------


@pytest.mark.slow
def test_dynamics_stay_in_robels_ranges_and_do_not_compound(
  dclaw_dynamics_task_id,
):
  task_id = dclaw_dynamics_task_id
  nominal_env = suite.load(*_fixed_counterpart(task_id), seed=0)
  nominal_env.reset()
  nominal = _snapshot(nominal_env.physics.model)
  env = suite.load(*task_id, seed=0)
  env.reset()  # composer compiles the model at the first reset.
  model = env.physics.model
  assert model.ngeom == nominal_env.physics.model.ngeom
  assert model.nbody == nominal_env.physics.model.nbody
  pose = _is_pose(task_id)
  assert env.task.dynamics == (
    randomization.DCLAW_POSE if pose else randomization.DCLAW_VALVE
  )
  # ROBEL randomizes every claw DOF (and the valve's): all DOFs here.
  assert model.nv == (9 if pose else 10)
  metal = np.all(nominal['geom_friction'] == _METAL_FRICTION, axis=1)
  plastic = nominal['geom_friction'][:, 0] == _PLASTIC_RATIO
  assert metal.sum() > 10 and plastic.sum() >= 4
  mount = model.name2id('mount', 'body')
  colored = np.zeros(model.ngeom, bool)
  if not pose:
    valve_body = model.name2id('valve/valve', 'body')
    colored[model.geom_bodyid == valve_body] = True
    colored[model.name2id('mount', 'geom')] = True
    assert colored.sum() == 5  # Mount + hub + 3 spokes.
    # The valve's geoms are plastic, so they keep their low friction.
    assert np.all(plastic[model.geom_bodyid == valve_body])

  previous = None
  for _ in range(_RESETS):
    env.reset()
    current = _snapshot(model)
    assert _within(current['dof_damping'], _DAMPING)
    assert _within(current['dof_frictionloss'], _FRICTION_LOSS)
    kp = _shared_kp(current, nominal)
    assert _within(kp[0], _KP)
    np.testing.assert_array_equal(current['body_mass'], nominal['body_mass'])
    np.testing.assert_array_equal(
      current['body_inertia'], nominal['body_inertia']
    )
    friction = current['geom_friction']
    rgba = current['geom_rgba']
    if pose:
      for name in ('geom_friction', 'body_pos', 'geom_rgba'):
        np.testing.assert_array_equal(current[name], nominal[name])
    else:
      _assert_valve_station_draw(current, nominal, mount, colored)
    if previous is not None:  # Fresh draws at every reset.
      assert np.all(current['dof_damping'] != previous['dof_damping'])
      assert np.all(current['dof_frictionloss'] != previous['dof_frictionloss'])
      assert kp[0] != previous['actuator_gainprm'][0, 0]
      if not pose:
        assert np.all(friction[0] != previous['geom_friction'][0])
        assert np.all(current['body_pos'][mount] != previous['body_pos'][mount])
        assert np.all(rgba[colored, :3] != previous['geom_rgba'][colored, :3])
    previous = current


def _shared_kp(current, nominal) -> np.ndarray:
  """The actuators' position gains, one draw for all; nothing else of the
  actuators changes."""
  kp = current['actuator_gainprm'][:, 0]
  assert np.all(kp == kp[0])
  np.testing.assert_array_equal(current['actuator_biasprm'][:, 1], -kp)
  np.testing.assert_array_equal(
    current['actuator_gainprm'][:, 1:], nominal['actuator_gainprm'][:, 1:]
  )
  np.testing.assert_array_equal(
    current['actuator_biasprm'][:, [0, 2]],
    nominal['actuator_biasprm'][:, [0, 2]],
  )
  return kp


def _assert_valve_station_draw(current, nominal, mount, colored) -> None:
  """The valve station's draw: one friction factor for every geom, the
  mount moved, the valve and mount recoloured; nothing else."""
  friction = current['geom_friction']
  metal = np.all(nominal['geom_friction'] == _METAL_FRICTION, axis=1)
  plastic = nominal['geom_friction'][:, 0] == _PLASTIC_RATIO
  # One draw for all geoms, relative to each geom's nominal friction.
  factor = friction / nominal['geom_friction']
  np.testing.assert_allclose(factor, factor[:1].repeat(len(factor), 0))
  metal_friction = friction[metal]
  assert _within(metal_friction[:, 0], _SLIDE)
  assert _within(metal_friction[:, 1], _SPIN)
  assert _within(metal_friction[:, 2], _ROLL)
  np.testing.assert_allclose(
    friction[plastic, 0], _PLASTIC_RATIO * metal_friction[0, 0]
  )
  # Only the mount moves, within +-1 cm of nominal.
  offset = current['body_pos'] - nominal['body_pos']
  assert np.all(np.abs(offset[mount]) <= _MOUNT_OFFSET)
  assert np.all(offset[mount] != 0)
  others = np.arange(len(offset)) != mount
  np.testing.assert_array_equal(offset[others], 0.0)
  rgba = current['geom_rgba']
  assert _within(rgba[colored, :3], _COLOR)
  np.testing.assert_array_equal(
    rgba[colored, 3], nominal['geom_rgba'][colored, 3]
  )
  np.testing.assert_array_equal(rgba[~colored], nominal['geom_rgba'][~colored])


@pytest.mark.slow
def test_nominal_variants_leave_the_model_alone(nominal_task_id):
  nominal_env = suite.load(*_fixed_counterpart(nominal_task_id), seed=0)
  nominal = _snapshot(nominal_env.physics.model)  # As built, never reset.
  env = suite.load(*nominal_task_id, seed=0)
  assert env.task.dynamics is None
  assert env.task.observation_noise == 0
  for _ in range(3):
    env.reset()
    env.step(np.full(env.action_spec().shape, 0.5))
    current = _snapshot(env.physics.model)
    for name in _MODEL_FIELDS:
      np.testing.assert_array_equal(current[name], nominal[name], name)


# --- total_mass (supported, unused by D'Claw) --------------------------------


def test_total_mass_rescales_without_compounding():
  claw = dclaw.DClaw()
  physics = mjcf.Physics.from_mjcf_model(claw.mjcf_model)
  model, data = physics.model, physics.data
  nominal_mass = model.body_mass.copy()
  nominal_inertia = model.body_inertia.copy()
  nominal_invweight = model.dof_invweight0.copy()
  nominal_total = nominal_mass.sum()
  bounds = (0.7 * nominal_total, 0.9 * nominal_total)
  randomizer = randomization.DynamicsRandomizer(
    randomization.DynamicsRanges(total_mass=randomization.Range(*bounds)),
    randomization.Targets(),
  )
  with pytest.raises(RuntimeError, match='after_compile'):
    randomizer.apply(physics, np.random.RandomState(0))
  randomizer.after_compile(physics)
  random_state = np.random.RandomState(0)
  totals = []
  for _ in range(_RESETS):
    randomizer.apply(physics, random_state)
    total = model.body_mass.sum()
    assert _within(total, bounds)
    # All masses and inertias scale together, from nominal each time.
    scale = total / nominal_total
    np.testing.assert_allclose(model.body_mass, scale * nominal_mass)
    np.testing.assert_allclose(model.body_inertia, scale * nominal_inertia)
    # Derived constants are up to date: they match a fresh mj_setConst.
    assert model.body_subtreemass[0] == pytest.approx(total)
    derived = (
      model.body_subtreemass.copy(),
      model.dof_invweight0.copy(),
      model.body_invweight0.copy(),
    )
    assert np.all(derived[1] != nominal_invweight)  # Lighter: recomputed.
    mujoco.mj_setConst(model.ptr, data.ptr)
    np.testing.assert_allclose(model.body_subtreemass, derived[0])
    np.testing.assert_allclose(model.dof_invweight0, derived[1])
    np.testing.assert_allclose(model.body_invweight0, derived[2])
    totals.append(total)
  assert len(set(totals)) == _RESETS


def test_claw_randomizer_touches_only_its_targets():
  claw = dclaw.DClaw()
  physics = mjcf.Physics.from_mjcf_model(claw.mjcf_model)
  model = physics.model
  nominal = _snapshot(model)
  ranges = dataclasses.replace(
    randomization.DCLAW_VALVE, damping_shared=True, friction_loss_shared=True
  )
  # Only the first finger's joints and actuators are targets.
  randomizer = randomization.DynamicsRandomizer(
    ranges,
    randomization.Targets(joints=claw.joints[:3], actuators=claw.actuators[:3]),
  )
  randomizer.after_compile(physics)
  randomizer.apply(physics, np.random.RandomState(1))
  damping = model.dof_damping
  assert np.all(damping[:3] == damping[0]) and _within(damping[0], _DAMPING)
  np.testing.assert_array_equal(damping[3:], nominal['dof_damping'][3:])
  friction_loss = model.dof_frictionloss
  assert np.all(friction_loss[:3] == friction_loss[0])
  assert _within(friction_loss[0], _FRICTION_LOSS)
  np.testing.assert_array_equal(friction_loss[3:], 0.0)
  gain = model.actuator_gainprm[:, 0]
  assert _within(gain[:3], _KP)
  np.testing.assert_array_equal(gain[3:], nominal['actuator_gainprm'][3:, 0])
  np.testing.assert_array_equal(model.actuator_biasprm[:, 1], -gain)
  # No mount and no coloured geoms given: positions and colours stay put.
  np.testing.assert_array_equal(model.body_pos, nominal['body_pos'])
  np.testing.assert_array_equal(model.geom_rgba, nominal['geom_rgba'])


# --- Observation noise -------------------------------------------------------


def _wrap(angle):
  return float(np.angle(np.exp(1j * angle)))


def _pose_reward(goal, qpos, qvel):
  """ROBEL's Pose reward and points (docs/robel_reference.md section 2.1)."""
  error = goal - qpos
  fast = np.abs(qvel) >= np.pi
  reward = -np.linalg.norm(error) - 0.1 * np.linalg.norm(qvel[fast])
  return reward, 1 - min(np.mean(np.abs(error)) / (np.pi / 4), 1)


def _valve_reward(goal, angle, qpos, qvel):
  """ROBEL's Turn/Screw reward and points.

  ROBEL's definition: docs/robel_reference.md section 2.2.
  """
  distance = abs(_wrap(goal - angle))
  fast = np.abs(qvel) >= 0.5
  reset_pose = np.tile([0.0, -np.pi / 3, np.pi / 3], 3)
  reward = (
    -5 * distance
    - np.linalg.norm(qpos - reset_pose)
    - np.linalg.norm(qvel[fast])
    + 10 * (distance < 0.25)
    + 50 * (distance < 0.1)
  )
  return reward, 1 - distance / np.pi


@pytest.mark.slow
def test_observation_noise_is_bounded_and_rewards_use_the_true_state(
  dclaw_dynamics_task_id,
):
  task_id = dclaw_dynamics_task_id
  pose = _is_pose(task_id)
  velocity_keys = ('qvel',) if pose else ('claw_qvel', 'object_qvel')
  env = suite.load(*task_id, seed=0)
  keys = env.task.agent_observation_keys + velocity_keys
  env = suite.load(*task_id, seed=0, task_kwargs={'observation_keys': keys})
  assert env.task.observation_noise == 0.05
  timestep = env.reset()  # Compiles the model: bind afterwards.
  claw = env.physics.bind(env.task.robot.joints)
  valve = None if pose else env.physics.bind(env.task.valve.hinge)
  rng = np.random.default_rng(9)
  ratios = {'qpos': [], 'qvel': [], 'valve': []}
  noisy_rewards_differ = False
  while True:
    obs = timestep.observation
    qpos, qvel = claw.qpos.copy(), claw.qvel.copy()
    observed_qpos = obs['qpos' if pose else 'claw_qpos']
    observed_qvel = obs['qvel' if pose else 'claw_qvel']
    ratios['qpos'].append(np.abs(observed_qpos - qpos) / _CLAW_QPOS_NOISE)
    ratios['qvel'].append(np.abs(observed_qvel - qvel) / _CLAW_QVEL_NOISE)
    goal = env.task.goal
    if pose:
      np.testing.assert_allclose(obs['qpos_error'], goal - observed_qpos)
      reward, points = _pose_reward(goal, qpos, qvel)
      noisy, _ = _pose_reward(goal, observed_qpos, observed_qvel)
    else:
      angle = float(valve.qpos[0])
      observed = np.arctan2(obs['object_y'][0], obs['object_x'][0])
      ratios['valve'].append(abs(_wrap(observed - angle)) / _VALVE_NOISE)
      np.testing.assert_allclose(
        obs['target_error'], [_wrap(goal - observed)], atol=1e-9
      )
      # The valve has no velocity range: ROBEL adds no velocity noise.
      np.testing.assert_array_equal(obs['object_qvel'], valve.qvel)
      reward, points = _valve_reward(goal, angle, qpos, qvel)
      noisy, _ = _valve_reward(goal, observed, observed_qpos, observed_qvel)
    assert float(obs['score']) == pytest.approx(points, abs=1e-12)
    if not timestep.first():
      assert timestep.reward == pytest.approx(reward, abs=1e-9)
      noisy_rewards_differ |= abs(noisy - reward) > 1e-6
    if timestep.last():
      break
    timestep = env.step(rng.uniform(-1, 1, 9))
  assert noisy_rewards_differ
  for name, values in ratios.items():
    if pose and name == 'valve':
      continue
    values = np.array(values)
    # Within ROBEL's half-widths, and actually spread over them.
    assert values.max() <= 1 + 1e-9, name
    assert np.all(values.max(axis=0) > 0.5), name


# --- The D'Kitty's RandomDynamics ---------------------------------------------


def _spread(values, bounds):
  """Fraction of the range `bounds` the values cover."""
  return (np.max(values) - np.min(values)) / (bounds[1] - bounds[0])


@pytest.mark.slow
def test_dkitty_dynamics_stay_in_robels_ranges_and_do_not_compound(
  dkitty_dynamics_task_id,
):
  task_id = dkitty_dynamics_task_id
  stand = robel_spec.family(task_id) == 'stand'
  kp_bounds = _KITTY_KP_STAND if stand else _KITTY_KP_WALK
  env = suite.load(*task_id, seed=0)
  assert env.task.dynamics == (
    randomization.DKITTY_STAND if stand else randomization.DKITTY_LOCOMOTION
  )
  model = env.physics.model
  # The model is compiled once, at construction: before the first reset it
  # is nominal, and agrees with the Fixed variant's (which has no terrain).
  nominal = _snapshot(model)
  fixed_env = suite.load(*_fixed_counterpart(task_id), seed=0)
  for name in ('dof_damping', 'dof_frictionloss', 'actuator_gainprm',
               'actuator_biasprm', 'body_mass', 'body_inertia'):  # fmt: skip
    np.testing.assert_array_equal(
      nominal[name], getattr(fixed_env.physics.model, name), name
    )
  assert model.ngeom == fixed_env.physics.model.ngeom + 1  # The terrain.
  legs = env.physics.bind(env.task.robot.joints).dofadr
  others = np.setdiff1d(np.arange(model.nv), legs)
  assert len(legs) == 12 and len(others) == 6  # The free joint.
  # ROBEL's friction draw is for its default friction, which every geom of
  # the D'Kitty and the floor has.
  np.testing.assert_array_equal(
    nominal['geom_friction'], np.tile(_METAL_FRICTION, (model.ngeom, 1))
  )

  previous = None
  draws = {'kp': [], 'mass': [], 'damping': []}
  for _ in range(_RESETS):
    env.reset()
    current = _snapshot(model)
    damping = _shared_leg_draw(current, nominal, 'dof_damping', legs)
    assert _within(damping, _KITTY_DAMPING)
    friction_loss = _shared_leg_draw(current, nominal, 'dof_frictionloss', legs)
    assert _within(friction_loss, _FRICTION_LOSS)
    kp = _shared_kp(current, nominal)
    assert len(kp) == 12 and _within(kp[0], kp_bounds)
    # One geom friction for all geoms, relative to the nominal friction.
    friction = current['geom_friction']
    np.testing.assert_array_equal(
      friction, friction[:1].repeat(len(friction), 0)
    )
    assert _within(friction[:, 0], _SLIDE)
    assert _within(friction[:, 1], _SPIN)
    assert _within(friction[:, 2], _ROLL)
    total = _scaled_mass(current, nominal, env.physics)
    # Nothing else moves or changes colour.
    np.testing.assert_array_equal(current['body_pos'], nominal['body_pos'])
    np.testing.assert_array_equal(current['geom_rgba'], nominal['geom_rgba'])
    if previous is not None:  # Fresh draws at every reset.
      assert damping != previous['dof_damping'][legs[0]]
      assert friction_loss != previous['dof_frictionloss'][legs[0]]
      assert kp[0] != previous['actuator_gainprm'][0, 0]
      assert np.all(friction[0] != previous['geom_friction'][0])
      assert total != previous['body_mass'].sum()
    previous = current
    draws['kp'].append(kp[0])
    draws['mass'].append(total)
    draws['damping'].append(damping)
  # The draws spread over the ranges (Stand's kp range is the wider one).
  assert _spread(draws['kp'], kp_bounds) > 0.6
  assert _spread(draws['mass'], _KITTY_MASS) > 0.6
  assert _spread(draws['damping'], _KITTY_DAMPING) > 0.6


def _shared_leg_draw(current, nominal, name, legs) -> float:
  """The value of `name` the leg DOFs share (one draw); the free joint's
  DOFs keep theirs."""
  values = current[name]
  assert np.all(values[legs] == values[legs[0]])
  others = np.setdiff1d(np.arange(len(values)), legs)
  np.testing.assert_array_equal(values[others], nominal[name][others])
  return values[legs[0]]


def _scaled_mass(current, nominal, physics) -> float:
  """The total mass, in ROBEL's range, with every body's mass and inertia
  scaled from nominal and the derived constants consistent with them."""
  model, data = physics.model, physics.data
  total = current['body_mass'].sum()
  assert _within(total, _KITTY_MASS)
  scale = total / nominal['body_mass'].sum()
  np.testing.assert_allclose(current['body_mass'], scale * nominal['body_mass'])
  np.testing.assert_allclose(
    current['body_inertia'], scale * nominal['body_inertia']
  )
  assert model.body_subtreemass[0] == pytest.approx(total, rel=1e-12)
  derived = (
    model.body_subtreemass.copy(),
    model.dof_invweight0.copy(),
    model.body_invweight0.copy(),
  )
  mujoco.mj_setConst(model.ptr, data.ptr)
  np.testing.assert_allclose(model.body_subtreemass, derived[0], rtol=1e-12)
  np.testing.assert_allclose(model.dof_invweight0, derived[1], rtol=1e-12)
  np.testing.assert_allclose(model.body_invweight0, derived[2], rtol=1e-12)
  return total


@pytest.mark.slow
def test_dkitty_observation_noise_is_on_the_legs_only(dkitty_dynamics_task_id):
  task_id = dkitty_dynamics_task_id
  family = robel_spec.family(task_id)
  env = suite.load(*task_id, seed=0)
  assert env.task.observation_noise == 0.05
  timestep = env.reset()
  physics = env.physics
  legs = physics.bind(env.task.robot.joints)
  torso = physics.bind(env.task.robot.torso)
  root = physics.bind(mjcf.get_frame_freejoint(env.task.robot.mjcf_model))
  policy = robel_spec.steady_policy(env)
  ratios = {'qpos': [], 'qvel': []}
  noisy_rewards_differ = False
  while True:
    obs = timestep.observation
    ratios['qpos'].append(
      np.abs(obs['kitty_qpos'] - legs.qpos) / _KITTY_QPOS_NOISE
    )
    ratios['qvel'].append(
      np.abs(obs['kitty_qvel'] - legs.qvel) / _KITTY_QVEL_NOISE
    )
    # The torso's features are exact.
    np.testing.assert_array_equal(obs['upright'], [torso.xmat[8]])
    np.testing.assert_allclose(
      obs['root_pos'], torso.xpos - [0.0, 0.0, 0.3], rtol=0, atol=1e-12
    )
    np.testing.assert_array_equal(obs['root_vel'], root.qvel[:3])
    xy = torso.xpos[:2]
    if family == 'stand':
      # pose_error is from the noisy joints; the reward from the true ones.
      np.testing.assert_allclose(obs['pose_error'], -obs['kitty_qpos'])
      cost = -4 * np.mean(np.abs(legs.qpos))
      noisy_cost = -4 * np.mean(np.abs(obs['kitty_qpos']))
      terms = env.task.reward_terms
      assert terms['pose_error_cost'] == pytest.approx(cost, abs=1e-12)
      noisy_rewards_differ |= abs(noisy_cost - cost) > 1e-6
      points = (1 - min(np.mean(np.abs(legs.qpos)) / (np.pi / 3), 1)) * (
        torso.xmat[8]
      )
      assert float(obs['score']) == pytest.approx(points, abs=1e-12)
    elif family == 'orient':
      np.testing.assert_array_equal(obs['current_facing'], torso.xmat[[1, 4]])
      to_target = env.task.target - xy
      np.testing.assert_allclose(
        obs['desired_facing'], to_target / np.linalg.norm(to_target)
      )
    else:
      np.testing.assert_allclose(
        obs['target_error'], env.task.target - xy, rtol=0, atol=1e-12
      )
    if timestep.last():
      break
    timestep = env.step(policy(timestep))
  if family == 'stand':
    assert noisy_rewards_differ
  for name, values in ratios.items():
    values = np.array(values)
    # Within ROBEL's half-widths, and actually spread over them.
    assert values.max() <= 1 + 1e-9, name
    assert np.all(values.max(axis=0) > 0.5), name
