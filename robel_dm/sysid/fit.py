"""Fits the simulated robot's joint dynamics to recorded excitation episodes.

The recorded joint targets are replayed on the excitation scene in MuJoCo,
from each episode's measured initial state, and the per-joint parameters
(kp, damping, friction loss, armature) and one control delay are chosen to
minimize the difference between simulated and measured joint angles,
velocities and, when the motors measured them, currents (scipy's bounded
trust-region least squares). The delay is searched over whole physics steps,
the rest is continuous. See docs/sysid.md.

Why currents: the angles of a position servo depend on kp, damping and
inertia almost only through their ratios; gravity and the measured current
(torque = kp * (target - angle)) fix their scale.
"""

import dataclasses
from typing import Any

from dm_control import mjcf
import mujoco
import numpy as np
from scipy import optimize, sparse

from robel_dm import calibration as calibration_lib
from robel_dm import recording
from robel_dm.hardware.dynamixel import control_table
from robel_dm.sysid import standard_errors as standard_errors_lib
from robel_dm.tasks import excitation

# Residual scales: a difference of this size counts as 1, so that angles,
# velocities and currents weigh alike. About 3 encoder ticks, 4 velocity
# units and 7 current units of an X430.
POSITION_SCALE = 0.005  # rad
VELOCITY_SCALE = 0.1  # rad/s
CURRENT_SCALE = 20.0  # mA
# Search bounds of each parameter as multiples of the model's value (kp,
# damping, armature) or in N m (friction loss).
RELATIVE_BOUNDS = (0.1, 10.0)
FRICTIONLOSS_BOUNDS = (1e-4, 0.5)  # N m
# Friction loss is optimized in these units (N m) and starts here.
FRICTIONLOSS_UNIT = 0.01
FRICTIONLOSS_START = 0.001
# A parameter whose relative standard error exceeds this (two standard
# errors over 15%), or that ends on a search bound, or any parameter of a
# fit that did not converge, is reported as poorly determined.
IDENTIFIED_UNCERTAINTY = 0.075
# Finite-difference step of the Jacobian, relative to the parameter.
DIFF_STEP = 1e-4


class SysidError(ValueError):
  """The recordings cannot be fitted (named)."""


@dataclasses.dataclass
class Trajectory:
  """One recorded excitation episode in joint space.

  Attributes:
    targets: joint targets, (steps + 1, joints), rad; row 0 is the goal
      the motors held at the reset, row k the one sent at step k.
    qpos: measured joint angles, (steps + 1, joints), rad.
    qvel: measured joint velocities, rad/s.
    current: measured currents in the joints' sense, mA, or None.
  """

  targets: np.ndarray
  qpos: np.ndarray
  qvel: np.ndarray
  current: np.ndarray | None


def load_trajectories(directory, domain: str) -> list[Trajectory]:
  """The excitation episodes of a recording directory.

  Raises:
    SysidError: if it holds no excitation episode of `domain`.
  """
  trajectories = []
  for episode in recording.read(directory):
    metadata = episode.metadata
    if metadata.get('kind') != 'excitation':
      continue
    if metadata.get('domain') != domain:
      raise SysidError(
        f'{directory}: episode {metadata.get("episode_index")} excites a '
        f'{metadata.get("domain")}, not a {domain}'
      )
    steps = episode.steps
    if len(episode) < 3:
      continue
    qpos = steps['observation.qpos']
    current = None
    if 'motor.current' in steps:
      robot = metadata.get('robot') or {}
      scales = [motor['scale'] for motor in robot.get('joints', ())]
      if len(scales) != qpos.shape[1]:
        raise SysidError(
          f'{directory}: episode {metadata["episode_index"]} has motor '
          'currents but no robot configuration to orient them'
        )
      joints = qpos.shape[1]
      current = steps['motor.current'][:, :joints] * np.asarray(scales)
    trajectories.append(
      Trajectory(
        targets=_sent_targets(steps['joint_targets'], metadata),
        qpos=qpos,
        qvel=steps['observation.qvel'],
        current=current,
      )
    )
  if not trajectories:
    raise SysidError(
      f'{directory} has no {domain} excitation episode (record one with '
      '`robel-sysid excite`)'
    )
  return trajectories


def _sent_targets(targets: np.ndarray, metadata: dict) -> np.ndarray:
  """The targets the motors acted on: a robot (or the virtual bus) receives
  each goal rounded to a whole encoder tick in the motor's frame (see
  `DynamixelClient.write_goal_positions`), the recording keeps the exact
  target. Up to half a tick (0.00077 rad) is a torque error of kp times
  that, the size of a small friction loss; replaying the exact targets
  biases kp by 1-2% (benchmarks/sysid.py). Recordings without a robot
  configuration (simulation) are returned as they are."""
  motors = (metadata.get('robot') or {}).get('joints') or ()
  if len(motors) != targets.shape[1] or not all(
    'scale' in m and 'offset' in m for m in motors
  ):
    return targets
  scale = np.array([float(m['scale']) for m in motors])
  offset = np.array([float(m['offset']) for m in motors])
  tick = control_table.RADIANS_PER_TICK
  ticks = np.rint((targets - offset) / scale / tick)
  return scale * ticks * tick + offset


class ReplaySimulator:
  """The excitation scene, replaying recorded targets with given dynamics."""

  def __init__(self, domain: str):
    task = excitation.JointExcitation(domain, duration=1.0)
    self._physics = mjcf.Physics.from_mjcf_model(task.root_entity.mjcf_model)
    self.model, self.data = self._physics.model.ptr, self._physics.data.ptr
    # The servos go wherever they are told, as on the virtual bus.
    self.model.actuator_ctrllimited[:] = 0
    joints = self._physics.bind(task.robot.joints)
    self.joint_names = tuple(joint.name for joint in task.robot.joints)
    self._qpos = np.asarray(joints.qposadr, int)
    self._dofs = np.asarray(joints.dofadr, int)
    self._actuators = np.asarray(
      self._physics.bind(task.robot.actuators).element_id, int
    )
    self.substeps = round(task.control_timestep / self.model.opt.timestep)
    self.timestep = float(self.model.opt.timestep)
    self.nominal = self.values()
    self.chains = self._chains(np.asarray(joints.element_id, int))

  def _chains(self, joint_ids: np.ndarray) -> np.ndarray:
    """Each joint's kinematic chain (a finger, a leg): the index of the
    topmost jointed body above it. The robot's base is fixed and nothing
    touches it, so one chain's motion does not depend on another's
    parameters."""
    model = self.model
    tops = []
    for joint in joint_ids:
      body = top = int(model.jnt_bodyid[joint])
      while body:
        if model.body_jntnum[body]:
          top = body
        body = int(model.body_parentid[body])
      tops.append(top)
    return np.unique(tops, return_inverse=True)[1]

  def values(self) -> dict[str, np.ndarray]:
    """The model's current parameters, per joint."""
    model = self.model
    return {
      'kp': model.actuator_gainprm[self._actuators, 0].copy(),
      'damping': model.dof_damping[self._dofs].copy(),
      'frictionloss': model.dof_frictionloss[self._dofs].copy(),
      'armature': model.dof_armature[self._dofs].copy(),
    }

  def set_values(self, values: dict[str, np.ndarray]) -> None:
    model = self.model
    for name, value in values.items():
      if name == 'kp':
        model.actuator_gainprm[self._actuators, 0] = value
        model.actuator_biasprm[self._actuators, 1] = -value
      else:
        getattr(model, f'dof_{name}')[self._dofs] = value
    # Constants derived from the inertia (the constraint solver's weights).
    mujoco.mj_setConst(model, self.data)

  def simulate(
    self, trajectory: Trajectory, delay_steps: int
  ) -> tuple[np.ndarray, ...]:
    """Joint angles, velocities and actuator forces after every step."""
    model, data = self.model, self.data
    mujoco.mj_resetData(model, data)
    data.qpos[self._qpos] = trajectory.qpos[0]
    data.qvel[self._dofs] = trajectory.qvel[0]
    data.ctrl[self._actuators] = trajectory.targets[0]
    mujoco.mj_forward(model, data)
    steps = len(trajectory.targets) - 1
    qpos = np.empty((steps, len(self._qpos)))
    qvel, force = np.empty_like(qpos), np.empty_like(qpos)
    rest = self.substeps - delay_steps
    for k in range(steps):
      if delay_steps:
        mujoco.mj_step(model, data, delay_steps)
      data.ctrl[self._actuators] = trajectory.targets[k + 1]
      mujoco.mj_step(model, data, rest)
      qpos[k] = data.qpos[self._qpos]
      qvel[k] = data.qvel[self._dofs]
      force[k] = data.actuator_force[self._actuators]
    return qpos, qvel, force


@dataclasses.dataclass
class FitResult:
  """A fit and how well it explains the recordings.

  Attributes:
    calibration: the fitted values (write it with `calibration.save`).
    joint_names: the joints, in action order.
    nominal: the model's values before the fit, parameter -> per joint.
    fitted: the fitted values, parameter -> per joint.
    standard_error: the standard error of each fitted value (its units),
      parameter -> per joint; inf if the recordings are too short to
      estimate one.
    uncertainty: the standard error relative to the value (friction loss:
      to at least its lower bound), parameter -> per joint.
    rms_before: per-joint RMS angle error of the model, rad.
    rms_after: per-joint RMS angle error of the fit, rad.
    control_delay: the fitted delay, s.
    poorly_determined: 'joint.parameter' -> why the recordings do not pin
      it down (a relative standard error over `IDENTIFIED_UNCERTAINTY`, a
      value on a search bound, a fit that did not converge).
    not_identified: the names of `poorly_determined`, in order.
    evaluations: simulations run.
  """

  calibration: calibration_lib.Calibration
  joint_names: tuple[str, ...]
  nominal: dict[str, np.ndarray]
  fitted: dict[str, np.ndarray]
  standard_error: dict[str, np.ndarray]
  uncertainty: dict[str, np.ndarray]
  rms_before: np.ndarray
  rms_after: np.ndarray
  control_delay: float
  poorly_determined: dict[str, str]
  not_identified: list[str]
  evaluations: int


class _Problem:
  """The least-squares problem of one delay."""

  def __init__(self, simulator, trajectories, parameters, use_current):
    self.simulator = simulator
    self.trajectories = trajectories
    self.parameters = parameters
    self.use_current = use_current
    self.joints = len(simulator.joint_names)
    self.evaluations = 0
    nominal = simulator.nominal
    self.unit = {
      name: (
        np.full(self.joints, FRICTIONLOSS_UNIT)
        if name == 'frictionloss'
        else nominal[name]
      )
      for name in parameters
    }

  def start(self) -> np.ndarray:
    start = []
    for name in self.parameters:
      if name == 'frictionloss':
        start.append(np.full(self.joints, FRICTIONLOSS_START))
      else:
        start.append(self.simulator.nominal[name])
    return self.scaled(dict(zip(self.parameters, start, strict=True)))

  def scaled(self, values) -> np.ndarray:
    return np.concatenate([values[n] / self.unit[n] for n in self.parameters])

  def values(self, x: np.ndarray) -> dict[str, np.ndarray]:
    parts = np.split(x, len(self.parameters))
    return {
      name: part * self.unit[name]
      for name, part in zip(self.parameters, parts, strict=True)
    }

  def bounds(self) -> tuple[np.ndarray, np.ndarray]:
    low, high = [], []
    for name in self.parameters:
      if name == 'frictionloss':
        bounds = np.array(FRICTIONLOSS_BOUNDS) / FRICTIONLOSS_UNIT
      else:
        bounds = np.array(RELATIVE_BOUNDS)
      low.append(np.full(self.joints, bounds[0]))
      high.append(np.full(self.joints, bounds[1]))
    return np.concatenate(low), np.concatenate(high)

  @property
  def components(self) -> int:
    """Residuals per joint and step: angle, velocity (, current)."""
    return 3 if self.use_current else 2

  @property
  def rows(self) -> int:
    steps = sum(len(t.targets) - 1 for t in self.trajectories)
    return steps * self.components * self.joints

  def angle_rms(self, residuals: np.ndarray) -> np.ndarray:
    """Per-joint RMS angle error (rad) of a residual vector."""
    angles = residuals.reshape(-1, self.components, self.joints)[:, 0]
    return np.sqrt(np.mean(np.square(angles), axis=0)) * POSITION_SCALE

  def residuals(self, x: np.ndarray | None, delay: int) -> np.ndarray:
    values = self.simulator.nominal if x is None else self.values(x)
    self.simulator.set_values(values)
    self.evaluations += 1
    parts = []
    for trajectory in self.trajectories:
      qpos, qvel, force = self.simulator.simulate(trajectory, delay)
      components = [
        (qpos - trajectory.qpos[1:]) / POSITION_SCALE,
        (qvel - trajectory.qvel[1:]) / VELOCITY_SCALE,
      ]
      if self.use_current:
        current = 1000.0 * force / control_table.TORQUE_PER_AMPERE
        components.append((current - trajectory.current[1:]) / CURRENT_SCALE)
      parts.append(np.stack(components, axis=1).ravel())
    return np.concatenate(parts)

  def sparsity(self) -> sparse.csr_matrix:
    """A joint's residuals depend on the parameters of its chain only."""
    chains = self.simulator.chains
    row_chain = chains[np.arange(self.rows) % self.joints]
    col_chain = np.tile(chains, len(self.parameters))
    return sparse.csr_matrix(row_chain[:, None] == col_chain[None, :])


def _best_delay(problem, x) -> int:
  costs = [
    float(np.sum(np.square(problem.residuals(x, delay))))
    for delay in range(problem.simulator.substeps)
  ]
  return int(np.argmin(costs))


def fit(
  trajectories: list[Trajectory],
  domain: str,
  *,
  parameters: tuple[str, ...] = calibration_lib.PARAMETERS,
  fit_delay: bool = True,
  use_currents: bool = True,
  max_evaluations: int = 200,
  source: dict[str, Any] | None = None,
) -> FitResult:
  """Fits joint dynamics (and the control delay) to excitation episodes.

  Args:
    trajectories: from `load_trajectories`.
    domain: 'dclaw' or 'dkitty'.
    parameters: which of `calibration.PARAMETERS` to fit; the others keep
      the model's values.
    fit_delay: search the control delay (else 0).
    use_currents: fit the measured currents too, when every trajectory has
      them.
    max_evaluations: function evaluations per least-squares fit (each
      Jacobian costs one simulation per parameter of a chain, plus one).
    source: recorded in the calibration's `fit` entry (e.g. directories).

  Returns:
    The fit.

  Raises:
    SysidError: for unknown parameters.
  """
  parameters = _checked_parameters(parameters)
  simulator = ReplaySimulator(domain)
  use_current = use_currents and all(
    t.current is not None for t in trajectories
  )
  problem = _Problem(simulator, trajectories, parameters, use_current)
  rms_before = problem.angle_rms(problem.residuals(None, 0))
  delay, result = _least_squares(problem, fit_delay, max_evaluations)
  return _fit_result(problem, domain, delay, result, rms_before, source)


def _checked_parameters(parameters: tuple[str, ...]) -> tuple[str, ...]:
  """The parameters to fit, in `calibration.PARAMETERS` order."""
  unknown = sorted(set(parameters) - set(calibration_lib.PARAMETERS))
  if unknown or not parameters:
    raise SysidError(
      f'parameters must be some of {calibration_lib.PARAMETERS}, got '
      f'{list(parameters)}'
    )
  return tuple(p for p in calibration_lib.PARAMETERS if p in parameters)


def _least_squares(problem, fit_delay: bool, max_evaluations: int):
  """The best delay (in physics steps) and scipy's least-squares result of
  the parameters at it."""
  x = problem.start()
  delay = _best_delay(problem, None) if fit_delay else 0
  bounds, sparsity = problem.bounds(), problem.sparsity()
  fits: dict[int, Any] = {}

  def fit_at(delay: int, start: np.ndarray):
    if delay not in fits:
      fits[delay] = optimize.least_squares(
        problem.residuals,
        start,
        bounds=bounds,
        jac_sparsity=sparsity,
        diff_step=DIFF_STEP,
        x_scale='jac',
        max_nfev=max_evaluations,
        args=(delay,),
      )
    return fits[delay]

  result = fit_at(delay, x)
  # The delay trades off against inertia and damping: walk to the
  # neighbouring delay while its (warm-started) fit is better.
  while fit_delay:
    neighbours = [
      d for d in (delay - 1, delay + 1) if 0 <= d < problem.simulator.substeps
    ]
    candidates = {d: fit_at(d, result.x) for d in neighbours}
    best = min(candidates, key=lambda d: candidates[d].cost)
    if candidates[best].cost >= result.cost:
      break
    delay, result = best, candidates[best]
  return delay, result


def _fit_result(
  problem, domain: str, delay: int, result, rms_before, source
) -> FitResult:
  """The least-squares `result` at `delay`, how well the recordings
  determine each value, written up as a calibration and a `FitResult`."""
  simulator, parameters = problem.simulator, problem.parameters
  trajectories = problem.trajectories
  fitted = problem.values(result.x)
  standard_error = standard_errors_lib.standard_errors(problem, result)
  uncertainty = {
    name: _relative(name, standard_error[name], fitted[name])
    for name in parameters
  }
  rms_after = problem.angle_rms(result.fun)
  names = simulator.joint_names
  poorly_determined = _poorly_determined(
    problem, fitted, uncertainty, problem.bounds(), converged=result.status > 0
  )
  control_delay = delay * simulator.timestep
  calibration = calibration_lib.Calibration(
    domain=domain,
    joints={
      names[j]: {name: float(fitted[name][j]) for name in parameters}
      for j in range(len(names))
    },
    control_delay=control_delay,
    fit={
      **(source or {}),
      'episodes': len(trajectories),
      'steps': int(sum(len(t.targets) - 1 for t in trajectories)),
      'used_currents': problem.use_current,
      'rms_angle_error_before': rms_before.tolist(),
      'rms_angle_error_after': rms_after.tolist(),
      'standard_error': {n: _json(e) for n, e in standard_error.items()},
      'relative_uncertainty': {n: _json(u) for n, u in uncertainty.items()},
      'not_identified': list(poorly_determined),
      'poorly_determined': poorly_determined,
    },
  )
  return FitResult(
    calibration=calibration,
    joint_names=names,
    nominal={name: simulator.nominal[name] for name in parameters},
    fitted=fitted,
    standard_error=standard_error,
    uncertainty=uncertainty,
    rms_before=rms_before,
    rms_after=rms_after,
    control_delay=control_delay,
    poorly_determined=poorly_determined,
    not_identified=list(poorly_determined),
    evaluations=problem.evaluations,
  )


def _json(values: np.ndarray) -> list[float | None]:
  """Per-joint values for the calibration file, None where not finite."""
  return [float(v) if np.isfinite(v) else None for v in values]


def _poorly_determined(
  problem, fitted, uncertainty, bounds, converged: bool
) -> dict[str, str]:
  """'joint.parameter' -> why it is poorly determined, for those that are."""
  names = problem.simulator.joint_names
  low, high = problem.values(bounds[0]), problem.values(bounds[1])
  reasons = {}
  for name in problem.parameters:
    for j, joint in enumerate(names):
      value, relative = fitted[name][j], uncertainty[name][j]
      if not converged:
        reason = 'the fit stopped at its evaluation limit, not converged'
      elif np.isclose(value, low[name][j], rtol=1e-3, atol=1e-6):
        reason = f'on the lower search bound {low[name][j]:.4g}'
      elif np.isclose(value, high[name][j], rtol=1e-3):
        reason = f'on the upper search bound {high[name][j]:.4g}'
      elif not np.isfinite(relative):
        reason = 'no standard error: the recordings are too short'
      elif relative > IDENTIFIED_UNCERTAINTY:
        reason = (
          f'standard error {relative:.1%} of the value (over '
          f'{IDENTIFIED_UNCERTAINTY:.1%})'
        )
      else:
        continue
      reasons[f'{joint}.{name}'] = reason
  return reasons


def _relative(name: str, error: np.ndarray, value: np.ndarray) -> np.ndarray:
  """A standard error relative to the value (friction loss: to at least
  its lower search bound, as it may be fitted to about 0)."""
  floor = FRICTIONLOSS_BOUNDS[0] if name == 'frictionloss' else 1e-12
  return error / np.maximum(value, floor)
