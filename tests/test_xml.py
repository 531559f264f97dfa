"""Model tests for the MJCF files under `xml/`.

Every model must compile, simulate 1 s under random in-range controls without
any MuJoCo warning, and reproduce the compiled facts recorded in
`xml/README.md` (masses, ranges, heights).
"""

import math
import pathlib

from dm_control import mjcf
import mujoco
import numpy as np
import pytest

_XML_DIR = pathlib.Path(__file__).resolve().parents[1] / 'xml'
_XML_FILES = sorted(_XML_DIR.glob('**/*.xml'))
_CLAW_XML = _XML_DIR / 'dclaw' / 'dclaw.xml'
_KITTY_XML = _XML_DIR / 'dkitty' / 'dkitty.xml'
_VALVE_XMLS = {
  'valve3': _XML_DIR / 'valve' / 'valve3.xml',
  'valve4': _XML_DIR / 'valve' / 'valve4.xml',
}

_SIM_STEPS = 400  # 1 s at the 0.0025 s timestep.
_CTRL_HOLD = 20  # Steps between control resamples.
_MOUNT_Z = 0.335  # Claw mount height in the valve scenes.

_ACTION_ORDER = (
  'FFJ10',
  'FFJ11',
  'FFJ12',
  'MFJ20',
  'MFJ21',
  'MFJ22',
  'THJ30',
  'THJ31',
  'THJ32',
)
_TOP = (-0.48, 0.48)
_MIDDLE = (-math.pi / 3, math.pi / 3)
_BOTTOM = (-math.pi / 2, math.pi / 2)
_ACTION_RANGES = np.array([_TOP, _MIDDLE, _BOTTOM] * 3)


def _mounted_claw():
  """Returns model and data of the claw with its root at z = 0.335, q = 0."""
  spec = mujoco.MjSpec.from_file(str(_CLAW_XML))
  spec.body('base_plate').pos = [0.0, 0.0, _MOUNT_Z]
  model = spec.compile()
  data = mujoco.MjData(model)
  mujoco.mj_forward(model, data)
  return model, data


def test_xml_files_found():
  """The glob finds the claw, both valves and the kitty."""
  names = {p.relative_to(_XML_DIR).as_posix() for p in _XML_FILES}
  assert {
    'dclaw/dclaw.xml',
    'valve/valve3.xml',
    'valve/valve4.xml',
    'dkitty/dkitty.xml',
  } <= names


@pytest.mark.parametrize(
  'path',
  _XML_FILES,
  ids=[p.relative_to(_XML_DIR).as_posix() for p in _XML_FILES],
)
def test_compiles_and_simulates_without_warnings(path):
  """Runs 1 s of random in-range control; no warnings, finite state.

  A root body without a joint (the D'Kitty torso) is welded to the world.
  """
  model = mujoco.MjModel.from_xml_path(str(path))
  data = mujoco.MjData(model)
  rng = np.random.default_rng(0)
  low, high = model.actuator_ctrlrange.T
  for step in range(_SIM_STEPS):
    if step % _CTRL_HOLD == 0:
      data.ctrl[:] = rng.uniform(low, high)
    mujoco.mj_step(model, data)
  for i, warning in enumerate(data.warning):
    assert warning.number == 0, f'{mujoco.mjtWarning(i).name} raised'
  for array in (data.qpos, data.qvel, data.qacc, data.act):
    assert np.all(np.isfinite(array))


def test_claw_total_mass():
  """Claw mass is 0.11 + 3 x 0.335 kg."""
  model = mujoco.MjModel.from_xml_path(str(_CLAW_XML))
  assert model.body_mass.sum() == pytest.approx(1.115, abs=1e-3)


def test_claw_joint_and_actuator_order():
  """Joints and actuators share names and follow the action order."""
  model = mujoco.MjModel.from_xml_path(str(_CLAW_XML))
  joints = tuple(model.joint(i).name for i in range(model.njnt))
  actuators = tuple(model.actuator(i).name for i in range(model.nu))
  assert joints == _ACTION_ORDER
  assert actuators == _ACTION_ORDER
  targets = tuple(
    model.joint(model.actuator_trnid[i, 0]).name for i in range(9)
  )
  assert targets == _ACTION_ORDER


def test_claw_actuators_are_position_servos_with_action_ranges():
  """Position servos (kp 2) whose ctrlrange is the action-map range."""
  model = mujoco.MjModel.from_xml_path(str(_CLAW_XML))
  np.testing.assert_allclose(
    model.actuator_ctrlrange, _ACTION_RANGES, atol=1e-12
  )
  assert np.all(model.actuator_ctrllimited)
  np.testing.assert_allclose(model.actuator_gainprm[:, 0], 2.0)
  np.testing.assert_allclose(
    model.actuator_biasprm[:, :3], [[0.0, -2.0, 0.0]] * 9
  )
  assert not np.any(model.actuator_forcelimited)


def test_claw_joint_ranges():
  """Joint limits as in ROBEL."""
  model = mujoco.MjModel.from_xml_path(str(_CLAW_XML))
  assert np.all(model.jnt_limited)
  np.testing.assert_allclose(
    model.jnt_range, [(-0.45, 1.35), (-2, 2), (-2, 2)] * 3
  )


def test_claw_mounted_heights():
  """Anchor, fingertip and finger-base positions with the mount at 0.335."""
  _, data = _mounted_claw()
  anchors_z = data.xanchor[:, 2].reshape(3, 3)  # finger x (top, mid, bottom)
  np.testing.assert_allclose(
    anchors_z, [[0.31775, 0.25025, 0.18225]] * 3, atol=5e-4
  )
  for tip in ('FFtip', 'MFtip', 'THtip'):
    assert data.site(tip).xpos[2] == pytest.approx(0.106, abs=5e-4)
  expected_xy = {
    'FFbase': (0.03, 0.052),
    'MFbase': (0.03, -0.052),
    'THbase': (-0.06, 0.0),
  }
  for body, xy in expected_xy.items():
    np.testing.assert_allclose(data.body(body).xpos[:2], xy, atol=1e-9)
  assert data.ncon == 0


@pytest.mark.parametrize(
  ('name', 'mass'), [('valve3', 0.476), ('valve4', 0.557)]
)
def test_valve_mass_and_unlimited_hinge(name, mass):
  """Density-1000 valve mass; one unlimited hinge."""
  model = mujoco.MjModel.from_xml_path(str(_VALVE_XMLS[name]))
  assert model.body('valve').mass[0] == pytest.approx(mass, abs=2e-3)
  assert model.njnt == 1 and model.jnt_limited[0] == 0
  assert model.joint(0).name == 'hinge'


@pytest.mark.parametrize('name', ['valve3', 'valve4'])
def test_valve_mark_points_to_world_x_at_zero(name):
  """At hinge angle 0 the mark lies along world +x."""
  model = mujoco.MjModel.from_xml_path(str(_VALVE_XMLS[name]))
  data = mujoco.MjData(model)
  mujoco.mj_forward(model, data)
  mark_axis = data.site('valve_mark').xmat.reshape(3, 3)[:, 2]
  np.testing.assert_allclose(mark_axis, (1.0, 0.0, 0.0), atol=1e-9)
  np.testing.assert_allclose(
    data.site('valve_mark').xpos[:2], (0.0375, 0.0), atol=1e-9
  )


@pytest.mark.parametrize('name', ['valve3', 'valve4'])
def test_dm_control_composes_claw_and_valve(name):
  """Both files parse with dm_control and compose without conflicts."""
  root = mjcf.RootElement(model='scene')
  mount = root.worldbody.add('site', name='mount', pos=(0.0, 0.0, _MOUNT_Z))
  mount.attach(mjcf.from_path(str(_CLAW_XML)))
  root.worldbody.attach(mjcf.from_path(str(_VALVE_XMLS[name])))
  physics = mjcf.Physics.from_mjcf_model(root)
  assert physics.model.opt.timestep == pytest.approx(0.0025)
  assert physics.model.nq == 10 and physics.model.nu == 9
  assert physics.model.jnt_limited[-1] == 0
  tips = physics.named.data.site_xpos[['dclaw/FFtip', 'dclaw/THtip']]
  np.testing.assert_allclose(tips[:, 2], 0.106, atol=5e-4)


# D'Kitty (docs/robel_reference.md section 3.4; action ranges: section 2.0).
_KITTY_ORDER = tuple(
  f'{leg}J{digit}{k}'
  for leg, digit in (('FR', 1), ('FL', 2), ('BL', 3), ('BR', 4))
  for k in range(3)
)
_KITTY_HIP = {'FR': 10, 'FL': 20, 'BL': 30, 'BR': 40}
_HIP_RIGHT = (-0.5, 0.279)
_HIP_LEFT = (-0.279, 0.5)
_UPPER = (0.0, math.pi / 2)
_KNEE = (-2.0, 0.0)
_KITTY_ACTION_RANGES = np.array(
  [_HIP_RIGHT, _UPPER, _KNEE, _HIP_LEFT, _UPPER, _KNEE]
  + [_HIP_LEFT, _UPPER, _KNEE, _HIP_RIGHT, _UPPER, _KNEE]
)
_KITTY_CROUCH = np.tile([0.0, math.pi / 4, -math.pi / 2], 4)


def _kitty_on_plane(qpos, torso_z):
  """Returns the kitty on a free joint above a plane at z 0, legs at qpos."""
  spec = mujoco.MjSpec.from_file(str(_KITTY_XML))
  spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[5, 5, 0.1])
  torso = spec.body('torso')
  torso.pos = [0.0, 0.0, torso_z]
  torso.add_freejoint()
  model = spec.compile()
  data = mujoco.MjData(model)
  data.qpos[7:] = qpos
  data.ctrl[:] = qpos
  mujoco.mj_forward(model, data)
  return model, data


def _self_contacts(model, data):
  """Contacts between two robot geoms (the plane is the world's)."""
  return [
    (model.body(model.geom_bodyid[c.geom1]).name,
     model.body(model.geom_bodyid[c.geom2]).name)
    for c in data.contact[: data.ncon]
    if model.geom_bodyid[c.geom1] and model.geom_bodyid[c.geom2]
  ]  # fmt: skip


def _assert_no_warnings(data):
  for i, warning in enumerate(data.warning):
    assert warning.number == 0, f'{mujoco.mjtWarning(i).name} raised'


def test_kitty_total_mass_and_massless_head():
  """1.834 kg: torso 0.72 + frame sphere 0.01 + 4 x 0.276; head is visual."""
  model = mujoco.MjModel.from_xml_path(str(_KITTY_XML))
  assert model.body_mass.sum() == pytest.approx(1.834, abs=1e-3)
  assert model.body('torso').mass[0] == pytest.approx(0.73, abs=1e-9)
  for leg, hip in _KITTY_HIP.items():
    masses = [model.body(f'{leg}{hip + k}').mass[0] for k in range(3)]
    np.testing.assert_allclose(masses, [0.118, 0.118, 0.040], atol=1e-9)
  head = model.geom('head')
  assert head.contype[0] == 0 and head.conaffinity[0] == 0
  assert model.body(head.bodyid[0]).name == 'torso'
  np.testing.assert_allclose(head.pos, (0.0, 0.104, 0.0))


def test_kitty_root_has_no_joint():
  """The arena adds the free joint; the file only has the 12 leg hinges."""
  model = mujoco.MjModel.from_xml_path(str(_KITTY_XML))
  assert model.body('torso').parentid[0] == 0
  assert model.body('torso').jntnum[0] == 0
  assert model.nq == model.nv == model.njnt == 12
  assert np.all(model.jnt_type == mujoco.mjtJoint.mjJNT_HINGE)
  assert model.opt.timestep == 0.0025
  assert model.opt.iterations == 100 and model.opt.tolerance == 1e-8


def test_kitty_joint_and_actuator_order():
  """Joints and actuators share names and follow the action order."""
  model = mujoco.MjModel.from_xml_path(str(_KITTY_XML))
  joints = tuple(model.joint(i).name for i in range(model.njnt))
  actuators = tuple(model.actuator(i).name for i in range(model.nu))
  assert joints == _KITTY_ORDER
  assert actuators == _KITTY_ORDER
  targets = tuple(
    model.joint(model.actuator_trnid[i, 0]).name for i in range(model.nu)
  )
  assert targets == _KITTY_ORDER


def test_kitty_actuators_and_joint_ranges():
  """kp-5 servos; ctrlrange = action range; joint ranges with exact pi."""
  model = mujoco.MjModel.from_xml_path(str(_KITTY_XML))
  np.testing.assert_allclose(
    model.actuator_ctrlrange, _KITTY_ACTION_RANGES, rtol=0, atol=1e-15
  )
  np.testing.assert_allclose(model.actuator_gainprm[:, 0], 5.0)
  np.testing.assert_allclose(
    model.actuator_biasprm[:, :3], [[0.0, -5.0, 0.0]] * 12
  )
  hip_right = (-(math.pi + 0.279), 0.279)
  hip_left = (-0.279, math.pi + 0.279)
  upper = (-2.14, 2.14)
  knee = (-math.pi / 2, math.pi / 2)
  np.testing.assert_allclose(
    model.jnt_range,
    [hip_right, upper, knee, hip_left, upper, knee]
    + [hip_left, upper, knee, hip_right, upper, knee],
    rtol=0,
    atol=1e-15,
  )
  assert np.all(model.jnt_limited)
  np.testing.assert_allclose(model.dof_damping, 1.0)
  np.testing.assert_allclose(model.dof_armature, 0.001)


def test_kitty_feet_and_leg_length():
  """Foot sites on the right legs (front = +y, right = +x); leg 0.292 m."""
  model, data = _kitty_on_plane(np.zeros(12), 0.0)
  for leg, hip in _KITTY_HIP.items():
    site = model.site(f'{leg}foot')
    assert model.body(site.bodyid[0]).name == f'{leg}{hip + 2}'
    foot = data.site(f'{leg}foot').xpos
    assert np.sign(foot[0]) == (1 if leg[1] == 'R' else -1)
    assert np.sign(foot[1]) == (1 if leg[0] == 'F' else -1)
    anchor = data.joint(f'{leg}J{hip}').xanchor
    np.testing.assert_allclose(anchor - foot, (0.0, 0.0, 0.292), atol=1e-9)
  capsule_bottom = min(
    data.geom_xpos[i, 2] - model.geom_size[i, :2].sum()
    for i in range(model.ngeom)
    if model.geom_type[i] == mujoco.mjtGeom.mjGEOM_CAPSULE
  )
  assert capsule_bottom == pytest.approx(-0.302, abs=1e-9)


def test_kitty_stands_upright_at_zero_pose():
  """Dropped from 0.31 at q = 0: settles at 0.302, upright for 5 s."""
  model, data = _kitty_on_plane(np.zeros(12), 0.31)
  assert not _self_contacts(model, data)
  min_upright = 1.0
  for _ in range(2000):  # 5 s.
    mujoco.mj_step(model, data)
    min_upright = min(min_upright, data.body('torso').xmat[8])
  _assert_no_warnings(data)
  assert min_upright > 0.99
  assert data.body('torso').xpos[2] == pytest.approx(0.302, abs=0.005)
  assert not _self_contacts(model, data)
  assert data.ncon == 4  # One per foot.


def test_kitty_crouched_height():
  """ROBEL's StandFixed start [0, pi/4, -pi/2] x 4 settles at z 0.244."""
  model, data = _kitty_on_plane(_KITTY_CROUCH, 0.26)
  assert not _self_contacts(model, data)
  for _ in range(400):  # 1 s.
    mujoco.mj_step(model, data)
  _assert_no_warnings(data)
  assert data.body('torso').xpos[2] == pytest.approx(0.244, abs=0.01)
  assert data.body('torso').xmat[8] > 0.99
  assert not _self_contacts(model, data)


def test_dm_control_attaches_kitty_with_free_joint():
  """The file parses with dm_control and composes on a free joint."""
  root = mjcf.RootElement(model='scene')
  frame = root.worldbody.attach(mjcf.from_path(str(_KITTY_XML)))
  frame.add('freejoint')
  physics = mjcf.Physics.from_mjcf_model(root)
  assert physics.model.nq == 19 and physics.model.nu == 12
  assert physics.model.opt.iterations == 100
  assert physics.model.body_mass.sum() == pytest.approx(1.834, abs=1e-3)
  cameras = [physics.model.camera(i) for i in range(physics.model.ncam)]
  assert {c.name for c in cameras} == {
    'dkitty/tracking_top',
    'dkitty/tracking_side',
  }
  assert all(
    c.mode[0] == mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM for c in cameras
  )
