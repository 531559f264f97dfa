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
  """The glob finds the claw and both valves."""
  names = {p.relative_to(_XML_DIR).as_posix() for p in _XML_FILES}
  assert {'dclaw/dclaw.xml', 'valve/valve3.xml', 'valve/valve4.xml'} <= names


@pytest.mark.parametrize(
  'path',
  _XML_FILES,
  ids=[p.relative_to(_XML_DIR).as_posix() for p in _XML_FILES],
)
def test_compiles_and_simulates_without_warnings(path):
  """Runs 1 s of random in-range control; no warnings, finite state."""
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
