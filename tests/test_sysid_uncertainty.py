"""System identification's standard errors and poorly-determined flags, on
short simulated excitations of a D'Claw with known dynamics and measurement
noise correlated in time (as quantized readings of moving joints are)."""

import numpy as np
import pytest

from robel_dm import suite
from robel_dm.hardware.dynamixel import control_table
from robel_dm.sysid import excite, fit, report
from robel_dm.tasks import excitation

# Every test fits (the quick tier, -m 'not slow', leaves them out).
pytestmark = pytest.mark.slow

PARAMETERS = ('kp', 'damping', 'frictionloss')
SECONDS = 3.0
# Measurement noise: AR(1) with this step-to-step correlation and these
# standard deviations (angle rad, velocity rad/s, current mA).
CORRELATION = 0.8
NOISE = (0.0006, 0.015, 3.0)


def _truth(frictionloss: float) -> dict[str, np.ndarray]:
  """A D'Claw unlike the model: kp and damping scaled per joint by a factor
  in [0.6, 1.6], the given friction loss, the model's armature (not
  fitted here)."""
  factors = np.random.default_rng(1).uniform(0.6, 1.6, (9, 2))
  return {
    'kp': 2.0 * factors[:, 0],
    'damping': 0.1 * factors[:, 1],
    'frictionloss': np.full(9, frictionloss),
    'armature': np.full(9, 0.001),
  }


def _recording(truth, seed=0) -> fit.Trajectory:
  """A steps excitation simulated with `truth`, measured with noise."""
  task = excitation.JointExcitation('dclaw', SECONDS)
  env = suite.load_excitation('dclaw', SECONDS)
  low, high = env.task.action_range(env.physics)
  env.close()
  names = tuple(joint.name for joint in task.robot.joints)
  targets = excite.targets(
    excite.Excitation(duration=SECONDS, seed=seed), names, task.center_pose,
    low, high, excitation.CONTROL_TIMESTEP,
  )  # fmt: skip
  targets = np.vstack([task.center_pose, targets])
  simulator = fit.ReplaySimulator('dclaw')
  simulator.set_values(truth)
  rest = np.zeros_like(targets)
  start = fit.Trajectory(targets, rest + task.center_pose, rest, None)
  qpos, qvel, force = simulator.simulate(start, delay_steps=0)
  current = 1000.0 * force / control_table.TORQUE_PER_AMPERE
  rng = np.random.default_rng(seed)

  def noisy(values, scale):
    noise = np.empty((len(targets), 9))
    noise[0] = rng.normal(0, scale, 9)
    step = scale * np.sqrt(1 - CORRELATION**2)
    for k in range(1, len(noise)):
      noise[k] = CORRELATION * noise[k - 1] + rng.normal(0, step, 9)
    return values + noise

  exact = [np.vstack([row, values]) for row, values in (
    (task.center_pose, qpos), (np.zeros(9), qvel), (np.zeros(9), current)
  )]  # fmt: skip
  return fit.Trajectory(
    targets, *(noisy(v, s) for v, s in zip(exact, NOISE, strict=True))
  )


def _fit(truth) -> fit.FitResult:
  return fit.fit(
    [_recording(truth)], 'dclaw', parameters=PARAMETERS, fit_delay=False
  )


@pytest.fixture(scope='module')
def well_determined():
  truth = _truth(frictionloss=0.03)
  return truth, _fit(truth)


def test_standard_errors_cover_the_true_errors(well_determined):
  truth, result = well_determined
  ratios = np.concatenate([
    np.abs(result.fitted[name] - truth[name]) / result.standard_error[name]
    for name in PARAMETERS
  ])  # fmt: skip
  # Every true error within 2.5 reported standard errors, half within one
  # (a Gaussian's: 99% and 68%). The Gauss-Newton covariance, which takes
  # the 300 correlated rows per joint as independent, fails both here.
  assert np.max(ratios) <= 2.5, ratios.round(2)
  assert np.median(ratios) <= 1.0, ratios.round(2)
  # ... and the errors are not covered by uselessly large ones.
  assert np.median(ratios) >= 0.2, ratios.round(2)
  assert np.all(result.uncertainty['kp'] < 0.02), result.uncertainty['kp']


def test_a_well_determined_fit_raises_no_flag(well_determined):
  _, result = well_determined
  assert result.poorly_determined == {}
  assert result.not_identified == []
  assert report.warning_lines(result) == []
  # Every row lines up with the header.
  table = report.fit_table(result).splitlines()[:10]  # Header, 9 joints.
  assert len({len(line) for line in table}) == 1


def test_low_friction_is_flagged_as_poorly_determined():
  truth = _truth(frictionloss=0.002)
  result = _fit(truth)
  friction = [f'{joint}.frictionloss' for joint in result.joint_names]
  assert sorted(result.poorly_determined) == sorted(friction)
  for name in friction:
    assert 'standard error' in result.poorly_determined[name]
  # kp and damping stay well determined.
  assert all(result.uncertainty['kp'] < 0.02)
  # The command prints one line per flagged value, after the table.
  lines = report.warning_lines(result)
  assert len(lines) == 9
  assert report.fit_table(result).splitlines()[-9:] == lines
  assert lines[0].startswith('? warning: FFJ10.frictionloss = ')
  assert 'poorly determined: standard error' in lines[0]
  assert result.calibration.fit['not_identified'] == friction
