"""A physics whose state comes from the robot's motors.

`HardwarePhysics` is an `mjcf.Physics` that does not integrate: once per
control step it sends the actuators' targets (`data.ctrl`) to the motors as
goal positions, waits for the control tick, reads the motors back, writes
their joint angles and velocities into `qpos`/`qvel`, advances `time` and
runs `mj_forward`. Every observable, reward and safety counter of the task
then works unchanged, from measured state.

An error during a step or a reset releases the motors, and the physics then
refuses to step until a reset has brought the robot back: the reset checks
that every motor answers again and takes its goals (see
`realize_initial_state`), then runs the reset procedure as usual.

Once freed (`env.close()`), the physics raises `PhysicsClosedError` on any
use of its model or data (rendering, stepping, reading it).
"""

import contextlib
import logging

from dm_control import mjcf
import mujoco
import numpy as np

from robel_dm.hardware import clock as clock_lib
from robel_dm.hardware import connection as connection_lib
from robel_dm.hardware import robot as robot_lib
from robel_dm.hardware import timing as timing_lib
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table

# Late control steps are logged at most this often, s (all are counted).
_OVERRUN_LOG_INTERVAL = 1.0


class PhysicsClosedError(RuntimeError, ReferenceError):
  """The physics was freed (its environment closed). A ReferenceError too,
  as dm_control raises for a freed simulated physics."""


class HardwarePhysics(mjcf.Physics):
  """mjcf.Physics driven by real (or virtual) motors. Call `attach` first."""

  _freed = False

  def free(self) -> None:
    super().free()
    self._freed = True

  def _check_open(self) -> None:
    if self._freed:
      raise PhysicsClosedError(
        'the environment is closed, its physics freed; load a new one to '
        'continue'
      )

  @property
  def model(self):
    self._check_open()
    return super().model

  @property
  def data(self):
    self._check_open()
    return super().data

  def attach(
    self,
    connection: connection_lib.Connection,
    joints,
    actuators,
    control_timestep: float,
    root_joint=None,
  ) -> None:
    """Connects the physics to the motors.

    Args:
      connection: the opened robot: its motors (joints first in action
        order, then auxiliaries), clock, auxiliary motors, joint limits,
        reset procedure, torso pose source and tracker.
      joints: the model's actuated joints, in action order.
      actuators: their actuators, in the same order.
      control_timestep: seconds per control step.
      root_joint: the model's free joint that the connection's torso source
        drives (a free-floating robot's), or None.
    """
    robot = connection.robot
    auxiliary_joints = connection.auxiliary_joints
    torso_source = connection.torso_source
    self._robot = robot
    self._clock = connection.clock
    self._reset = connection.reset
    self._tracker = connection.tracker
    self._period = control_timestep
    # The achieved period and late steps of every control step.
    self.timing = timing_lib.ControlTiming(control_timestep)
    self._substeps = max(1, round(control_timestep / self.model.opt.timestep))
    self._pending_substeps = 0
    # Auxiliary motors with a model joint (the valve) write qpos/qvel like
    # the robot's joints; the others (the guide) are exposed as
    # `auxiliary_angles` and take goals from `auxiliary_goals`.
    modelled = {n: j for n, j in auxiliary_joints.items() if j is not None}
    self._free_auxiliaries = tuple(
      n for n, j in auxiliary_joints.items() if j is None
    )
    bound = self.bind(list(joints) + list(modelled.values()))
    self._qpos_index = np.asarray(bound.qposadr, int)
    self._qvel_index = np.asarray(bound.dofadr, int)
    self.auxiliary_angles: dict[str, float] = {}  # rad, read every step.
    self.auxiliary_goals: dict[str, float] = {}  # rad, sent every step.
    self._ctrl_index = np.asarray(self.bind(list(actuators)).element_id, int)
    self._n_joints = len(joints)
    self._auxiliary_names = tuple(modelled)
    ctrl_range = self.bind(list(actuators)).ctrlrange
    robot.set_joint_limits(
      ctrl_range[:, 0], ctrl_range[:, 1], connection.joint_limits
    )
    self.motor_currents = np.zeros(len(joints))  # mA, updated every step.
    self._torso_source = torso_source
    if torso_source is not None:
      root = self.bind(root_joint)
      self._root_qpos = int(root.qposadr)
      self._root_dof = int(root.dofadr)
    self._next_tick = None
    self._last_overrun_log = -np.inf
    self._resetting = False
    # The error after which the motors were released: no step until a reset
    # has checked the bus and re-enabled them.
    self._fault: BaseException | None = None

  @property
  def robot(self) -> robot_lib.HardwareRobot:
    return self._robot

  @property
  def clock(self) -> clock_lib.Clock:
    """What paces the control loop (wall or simulated time)."""
    return self._clock

  @contextlib.contextmanager
  def reset_context(self):
    # While the task sets up an episode, simulated settling steps must not
    # reach the motors: `realize_initial_state` moves them.
    self._resetting = True
    try:
      with super().reset_context():
        yield self
    finally:
      self._resetting = False

  def step(self, nstep: int = 1) -> None:
    """Exchanges with the motors once per control step (its last substep)."""
    self._check_open()
    if self._resetting:
      return
    self._pending_substeps += nstep
    if self._pending_substeps < self._substeps:
      return
    self._pending_substeps = 0
    if self._fault is not None:
      raise dynamixel.RobotReleasedError(
        f'the robot was released after an error ({self._fault!r}); reset() '
        'checks the bus and re-enables the motors before it steps again'
      )
    try:
      self._robot.write_joint_goals(self.data.ctrl[self._ctrl_index])
      for name, goal in self.auxiliary_goals.items():
        self._robot.write_auxiliary_goal(name, goal)
      self._wait_for_tick()
      self._read_motors()
      self._robot.check_health()
    except BaseException as error:
      # An error, Ctrl-C or a motor fault: never leave the motors powered,
      # and never step on with them released.
      self._fault = error
      self._robot.release()
      raise
    self.data.time += self._substeps * self.model.opt.timestep
    mujoco.mj_forward(self.model.ptr, self.data.ptr)

  def realize_initial_state(self) -> None:
    """Brings the motors to the joint state the task set, then reads back.

    Runs the reset procedure (see `resets`); auxiliary motors (the valve)
    are driven to their initial angle and then released for the episode.
    After an error (the robot was released), the robot is first brought
    back (see `_recover`). If anything fails, the motors are released
    again and the physics keeps refusing to step.

    Raises:
      dynamixel.DynamixelError: naming the motors that failed; after an
        error, its message says that the robot could not be brought back.
      resets.ResetError: if the reset procedure failed.
    """
    fault, self._fault = self._fault, RuntimeError('reset did not finish')
    try:
      if fault is not None:
        self._recover()
      # The bus first: every motor answers, none reports a hardware error.
      self._robot.check_health(force=True)
      desired = np.array(self._robot.positions)
      desired[: len(self._qpos_index)] = self.data.qpos[self._qpos_index]
      robot = self._robot
      auxiliary_goals = {
        name: desired[robot.auxiliary_index(name)]
        for name in self._auxiliary_names
      }
      # E.g. the guide motor showing the goal (set by the task).
      auxiliary_goals.update(self.auxiliary_goals)
      self._reset(
        robot,
        self._clock,
        robot.reset_goals(desired[: self._n_joints]),
        auxiliary_goals,
      )
      # Resets release the auxiliary motors; those still commanded (a guide
      # showing the goal) are held.
      held = [robot.auxiliary_id(name) for name in self.auxiliary_goals]
      if held:
        robot.set_torque(True, held)
      if self._tracker is not None:
        # The robot stands where the episode starts: that is the origin.
        self._tracker.calibrate_origin()
      robot.check_health(force=True)
      self._read_motors()
    except BaseException as error:
      self._fault = error
      self._robot.release()
      if fault is not None and isinstance(error, dynamixel.DynamixelError):
        self._fault = _not_recovered(error)
        raise self._fault from error
      raise
    self._fault = None
    self.data.time = 0.0
    self._pending_substeps = 0
    self._next_tick = self._clock.now() + self._period
    self.timing.restart()
    mujoco.mj_forward(self.model.ptr, self.data.ptr)

  def _recover(self) -> None:
    """Checks the bus after an error, before the reset procedure runs.

    Every motor is released (one that was away when the error released the
    robot may still hold its torque) and must answer a ping as the model it
    was at connection. Then every motor is sent the goal it already holds
    (torque is off: nothing moves) and the state is read back, which
    confirms every goal to the client: a goal write that the failed step
    lost must not fail the reset's reads (a client that counts lost goal
    writes until a read finds the goal arrived would fail every read).

    Raises:
      dynamixel.MissingMotorError: naming the motors that do not answer.
      dynamixel.DynamixelError: for a motor of another model, or goal
        writes that are still lost.
    """
    robot, client = self._robot, self._robot.client
    robot.release()
    missing, models = [], client.models
    for motor_id in client.motor_ids:
      try:
        model = client.ping(motor_id)
      except dynamixel.MissingMotorError:
        missing.append(motor_id)
        continue
      if model != models[motor_id]:
        raise dynamixel.DynamixelError(
          f'motor {motor_id} is now a model {model}, was a model '
          f'{models[motor_id]}',
          [motor_id],
        )
    if missing:
      raise dynamixel.MissingMotorError(
        f'motors {missing} do not answer a ping (no reply, or a corrupted '
        'one): check their cables and power',
        missing,
      )
    goals = client.sync_read_register(table.GOAL_POSITION)
    ids = client.motor_ids
    client.write_goal_positions(
      [goals[i] * table.RADIANS_PER_TICK for i in ids], ids
    )
    robot.read()

  def _wait_for_tick(self) -> None:
    clock = self._clock
    now = clock.now()
    if self._next_tick is None:
      self._next_tick = now + self._period
    late = now - self._next_tick
    clock.sleep_until(self._next_tick)
    is_late = self.timing.record(late, clock.now())
    if is_late and now - self._last_overrun_log > _OVERRUN_LOG_INTERVAL:
      logging.warning(
        'control step %.1f ms late (%d late so far)',
        late * 1e3,
        self.timing.late_steps,
      )
      self._last_overrun_log = now
    # After an overrun, keep the period from now rather than bursting.
    self._next_tick = max(self._next_tick, now) + self._period

  def _read_motors(self) -> None:
    robot = self._robot
    robot.read()
    modelled = len(self._qpos_index)
    self.data.qpos[self._qpos_index] = robot.positions[:modelled]
    self.data.qvel[self._qvel_index] = robot.velocities[:modelled]
    for name in self._free_auxiliaries:
      self.auxiliary_angles[name] = float(
        robot.positions[robot.auxiliary_index(name)]
      )
    self.motor_currents[:] = robot.currents[: self._n_joints]
    if self._torso_source is not None:
      position, quaternion, velocity, angular_velocity = self._torso_source()
      qpos, dof = self._root_qpos, self._root_dof
      self.data.qpos[qpos : qpos + 3] = position
      self.data.qpos[qpos + 3 : qpos + 7] = quaternion
      self.data.qvel[dof : dof + 3] = velocity
      self.data.qvel[dof + 3 : dof + 6] = angular_velocity


def _not_recovered(error: dynamixel.DynamixelError) -> dynamixel.DynamixelError:
  """`error` again (same class, same motors), saying that the robot could
  not be brought back after an earlier error."""
  message = (
    f'reset could not bring the robot back after an error: {error}; the '
    'motors that answer are released (torque off)'
  )
  if isinstance(error, dynamixel.MotorFaultError):
    return dynamixel.MotorFaultError(message, error.errors)
  return type(error)(message, error.motor_ids)
