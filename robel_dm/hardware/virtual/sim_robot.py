"""A MuJoCo-simulated robot behind the virtual servo bus.

`SimulatedRobot` is a virtual-bus `Driver`: it simulates the task's scene
(robot, valve, floor) and turns the goal positions and torque switches the
bus receives into actuator targets, and the simulated joints back into the
motors' present position, velocity and current, through the same
calibration a real robot's configuration describes. Time advances either on
request (`advance`, used by a `SimulatedClock`: deterministic, as fast as
the machine allows) or with the wall clock (a standalone bus).
"""

import threading
import time

from dm_control import composer
import mujoco
import numpy as np

from robel_dm.hardware import config as config_lib
from robel_dm.hardware.dynamixel import control_table as table

# Position gain (N m/rad) and damping (N m s/rad) of an auxiliary motor
# holding a goal (the valve during resets); it has no actuator in the model.
_AUXILIARY_KP = 2.0
_AUXILIARY_KV = 0.1

# Simulated time one read catches up at most, s (see `on_read`).
_MAX_CATCH_UP = 1.0


class SimulatedRobot:
  """Simulates a task's robot for the virtual bus (thread-safe)."""

  def __init__(
    self,
    scene: composer.Environment,
    robot_config: config_lib.RobotConfig,
    realtime: bool = False,
  ):
    """Builds the simulation.

    Args:
      scene: a simulated environment of a task whose scene holds every
        joint the configuration's motors measure (e.g. a D'Claw valve task
        for the valve motor), built with no time limit. The simulation owns
        it from now on (and closes it).
      robot_config: motor IDs and calibration.
      realtime: advance with the wall clock on every bus access, instead
        of only when `advance` is called.

    Raises:
      config_lib.ConfigError: if the configuration's joints are not the
        scene's robot's.
    """
    self._config = robot_config
    self._env = scene
    self._env.reset()
    physics = self._env.physics
    self._model, self._data = physics.model.ptr, physics.data.ptr
    self._lock = threading.RLock()
    task_instance = self._env.task
    robot = task_instance.robot
    joint_names = [joint.name for joint in robot.joints]
    if [m.name for m in self._config.joints] != joint_names:
      raise config_lib.ConfigError(
        f'{self._config.source}: joints '
        f'{[m.name for m in self._config.joints]} do not match the model '
        f'{joint_names}'
      )
    # Motor ID -> (motor, qpos address, dof address, actuator id or None).
    self._motors = {}
    bound = physics.bind(robot.joints)
    actuator_ids = physics.bind(robot.actuators).element_id
    for i, motor in enumerate(self._config.joints):
      self._motors[motor.id] = (
        motor,
        int(bound.qposadr[i]),
        int(bound.dofadr[i]),
        int(actuator_ids[i]),
      )
    for name, joint in task_instance.auxiliary_joints().items():
      motor = self._config.auxiliary_motor(name)
      if motor is not None:
        element = physics.bind(joint)
        self._motors[motor.id] = (
          motor,
          int(element.qposadr),
          int(element.dofadr),
          None,
        )
    self._nominal_gain = self._model.actuator_gainprm[:, 0].copy()
    # A servo goes wherever it is told (within its joint's mechanical
    # limits): the action range is the robot layer's business, and scripted
    # resets command poses beyond it on purpose.
    self._model.actuator_ctrllimited[:] = 0
    self._auxiliary_goals: dict[int, float] = {}  # dof -> goal, rad.
    self._root = task_instance.root_joint
    # The state a person puts a fallen robot back in (`place_at_start`).
    self._start_qpos = self._data.qpos.copy()
    # A calibrated control delay of the scene: goals take effect this many
    # physics steps after they arrive (FIFO of [steps left, actuator, goal]).
    self._delay_steps = round(
      self._env.control_delay / self._model.opt.timestep
    )
    self._pending_goals: list[list] = []
    self._realtime = realtime
    self._last_wall_time = time.monotonic()
    # A calibrated robot's position sensors are noisy (seeded: repeatable).
    calibration = self._env.calibration
    self._sensor_noise = calibration.sensor_noise if calibration else 0.0
    self._noise = np.random.default_rng(0)

  @property
  def motor_ids(self) -> tuple[int, ...]:
    return tuple(self._motors)

  @property
  def physics(self):
    return self._env.physics

  def close(self) -> None:
    self._env.close()

  # --- virtual.Driver --------------------------------------------------------

  def on_write(self, servos, ids) -> None:
    with self._lock:
      for motor_id in ids:
        if motor_id not in self._motors:
          # A motor outside the model (the guide): an ideal servo.
          servo = servos[motor_id]
          if servo.torque_enabled:
            servo.set_present(servo.goal_position, 0, 0)
          continue
        motor, _, dof, actuator = self._motors[motor_id]
        servo = servos[motor_id]
        goal = motor.to_joint(servo.goal_position * table.RADIANS_PER_TICK)
        if actuator is None:
          if servo.torque_enabled:
            self._auxiliary_goals[dof] = goal
          else:
            self._auxiliary_goals.pop(dof, None)
          continue
        if self._delay_steps:
          self._pending_goals.append([self._delay_steps, actuator, goal])
        else:
          self._data.ctrl[actuator] = goal
        # Torque off: the servo no longer holds (no position gain).
        kp = self._nominal_gain[actuator] if servo.torque_enabled else 0.0
        self._model.actuator_gainprm[actuator, 0] = kp
        self._model.actuator_biasprm[actuator, 1] = -kp

  def on_read(self, servos, ids) -> None:
    with self._lock:
      if self._realtime:
        now = time.monotonic()
        # After an idle spell the robot has long settled: simulating all of
        # it would hold the reply past the client's deadline.
        idle = now - self._last_wall_time
        self._advance_locked(min(idle, _MAX_CATCH_UP))
        self._last_wall_time = now
      for motor_id in ids:
        if motor_id not in self._motors:
          continue
        motor, qpos, dof, actuator = self._motors[motor_id]
        servo = servos[motor_id]
        angle = motor.to_motor(self._data.qpos[qpos])
        if self._sensor_noise:
          angle += self._noise.normal(0.0, self._sensor_noise)
        velocity = self._data.qvel[dof] / motor.scale
        force = 0.0 if actuator is None else self._data.actuator_force[actuator]
        unit = table.MODELS.get(servo.model_number, ('', 2.69))[1]
        current = 1000.0 * force / table.TORQUE_PER_AMPERE / motor.scale / unit
        # The servo's firmware caps its current at the Current Limit.
        limit = servo.get(table.CURRENT_LIMIT)
        current = min(max(current, -limit), limit)
        servo.set_present(
          int(round(angle / table.RADIANS_PER_TICK)),
          int(round(velocity / table.RADIANS_PER_SECOND_PER_UNIT)),
          int(round(current)),
        )

  # --- Time ------------------------------------------------------------------

  def advance(self, seconds: float) -> None:
    """Simulates `seconds` more (rounded to whole physics steps)."""
    with self._lock:
      self._advance_locked(seconds)

  def _advance_locked(self, seconds: float) -> None:
    steps = int(round(seconds / self._model.opt.timestep))
    pending = self._pending_goals
    while pending and pending[0][0] <= steps:
      # Up to the next delayed goal, then apply it.
      due = pending[0][0]
      self._step_locked(due)
      steps -= due
      for goal in pending:
        goal[0] -= due
      while pending and pending[0][0] <= 0:
        _, actuator, goal = pending.pop(0)
        self._data.ctrl[actuator] = goal
    for goal in pending:
      goal[0] -= steps
    self._step_locked(steps)

  def _step_locked(self, steps: int) -> None:
    if steps <= 0:
      return
    if not self._auxiliary_goals:
      mujoco.mj_step(self._model, self._data, steps)
      return
    applied = self._data.qfrc_applied
    for _ in range(steps):
      for dof, goal in self._auxiliary_goals.items():
        error = goal - self._data.qpos[self._dof_qpos(dof)]
        applied[dof] = (
          _AUXILIARY_KP * error - _AUXILIARY_KV * self._data.qvel[dof]
        )
      mujoco.mj_step(self._model, self._data)
    for dof in self._auxiliary_goals:
      applied[dof] = 0.0

  def _dof_qpos(self, dof: int) -> int:
    joint = self._model.dof_jntid[dof]
    return int(self._model.jnt_qposadr[joint])

  # --- Free-floating robots ------------------------------------------------

  def place_at_start(self) -> None:
    """What a person does for a fallen robot: stands it on its start mark
    in its initial pose, at rest (the scene's state after its reset).

    Raises:
      ValueError: if the robot is not free-floating.
    """
    if self._root is None:
      raise ValueError('this robot has no free-floating torso to place')
    with self._lock:
      self._data.qpos[:] = self._start_qpos
      self._data.qvel[:] = 0.0
      self._data.act[:] = 0.0
      mujoco.mj_forward(self._model, self._data)

  def torso_pose(self):
    """The simulated root's position, quaternion, velocity and body rates.

    Raises:
      ValueError: if the robot is not free-floating.
    """
    if self._root is None:
      raise ValueError('this robot has no free-floating torso')
    with self._lock:
      root = self.physics.bind(self._root)
      qpos, dof = int(root.qposadr), int(root.dofadr)
      return (
        self._data.qpos[qpos : qpos + 3].copy(),
        self._data.qpos[qpos + 3 : qpos + 7].copy(),
        self._data.qvel[dof : dof + 3].copy(),
        self._data.qvel[dof + 3 : dof + 6].copy(),
      )
