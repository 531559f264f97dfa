"""Environments whose physics is a real (or virtual) robot.

`make_environment` connects to the motors of a robot configuration, checks
them, and returns a `HardwareEnvironment`: the task's own environment with a
`HardwarePhysics` underneath. The motors are released (torque off) when the
environment closes, when a step fails or is interrupted (Ctrl-C), on SIGTERM
and at interpreter exit.

`device_path='virtual'` runs the same code against an in-process virtual
servo bus whose motors a MuJoCo simulation of the task drives, in simulated
time (fast, deterministic, no hardware needed).
"""

import signal
import threading

from dm_control import composer

from robel_dm import environment as environment_lib
from robel_dm.hardware import clock as clock_lib
from robel_dm.hardware import config as config_lib
from robel_dm.hardware import dynamixel, resets
from robel_dm.hardware import physics as physics_lib
from robel_dm.hardware import robot as robot_lib

VIRTUAL_DEVICE = 'virtual'


class HardwareEnvironment(environment_lib.Environment):
  """A robel_dm environment on motors; see `make_environment`."""

  def __init__(self, task: composer.Task, *, hardware: dict, **kwargs):
    self._hardware = hardware
    self._closed = False
    super().__init__(task, **kwargs)

  @property
  def robot(self) -> robot_lib.HardwareRobot:
    return self._hardware['robot']

  @property
  def virtual_bus(self):
    """The in-process virtual bus (device 'virtual'), else None."""
    return self._hardware.get('bus')

  @property
  def simulated_robot(self):
    """The simulation behind the virtual bus (device 'virtual'), else None."""
    return self._hardware.get('simulation')

  def _recompile_physics(self):
    physics = getattr(self, '_physics', None)
    if physics:
      physics.free()
    self._physics = physics_lib.HardwarePhysics.from_mjcf_model(
      self._task.root_entity.mjcf_model
    )
    self._physics.legacy_step = self._legacy_step
    hardware = self._hardware
    task = self._task
    self._physics.attach(
      robot=hardware['robot'],
      joints=task.robot.joints,
      actuators=task.robot.actuators,
      auxiliary_joints=hardware['auxiliary_joints'],
      clock=hardware['clock'],
      control_timestep=task.control_timestep,
      torso_source=hardware.get('torso_source'),
      root_joint=hardware.get('root_joint'),
      joint_limits=hardware.get('joint_limits'),
      reset=hardware.get('reset'),
      tracker=hardware.get('tracker'),
    )

  def _prepare_batching(self) -> None:
    super()._prepare_batching()
    self._direct_mujoco = False  # Every step goes through the motors.

  def close(self) -> None:
    """Releases the motors, closes the port (and the virtual bus)."""
    if self._closed:
      return
    self._closed = True
    try:
      self._hardware['robot'].release()
      self._hardware['robot'].client.disconnect()
    finally:
      for stop in self._hardware.get('on_close', ()):
        stop()
      super().close()

  def __enter__(self) -> 'HardwareEnvironment':
    return self

  def __exit__(self, *exc_info) -> None:
    self.close()


def _install_sigterm_handler() -> None:
  """Makes SIGTERM exit through Python (so atexit releases the motors)."""
  if threading.current_thread() is not threading.main_thread():
    return
  if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:

    def _exit(signum, frame):
      del frame
      raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, _exit)


def make_environment(
  task: composer.Task,
  *,
  domain: str,
  task_name: str,
  device_path: str,
  robot_config: config_lib.RobotConfig | str | None = None,
  task_kwargs=None,
  seed=None,
  torso_source=None,
  reset: str | None = None,
  tracker=None,
  **environment_kwargs,
) -> HardwareEnvironment:
  """Connects `task` to a robot.

  Args:
    task: the task (built as for simulation).
    domain: 'dclaw' or 'dkitty'.
    task_name: the task's registry name (for the virtual bus's scene).
    device_path: serial device of the Dynamixel bus, or 'virtual'.
    robot_config: a `RobotConfig`, a path to a JSON configuration, or None
      for ROBEL's configuration of the domain.
    task_kwargs: the task's arguments (for the virtual bus's scene).
    seed: seed of the virtual bus's scene.
    torso_source: for a free-floating robot (D'Kitty) on a real bus: a
      callable returning the torso's (position, quaternion, linear
      velocity, angular velocity in the torso frame).
    reset: 'scripted' (ROBEL's scripted resets; the default of the D'Claw's
      valve tasks), 'move' (one blocking move; the default otherwise),
      'manual' (a person places the robot), or a procedure (see `resets`).
    tracker: a `tracking.TorsoTracker` for a free-floating robot: the torso
      pose source (also on the virtual bus), recalibrated at every reset,
      and the source of Orient/Walk targets if it tracks them. Closed with
      the environment.
    **environment_kwargs: forwarded to the environment.

  Returns:
    The environment; close it (or use it as a context manager).

  Raises:
    config_lib.ConfigError: for a malformed configuration.
    dynamixel.DynamixelError: if the port or a motor is not there.
    ValueError: if the task needs a sensor this robot setup lacks.
  """
  if isinstance(robot_config, str):
    robot_config = config_lib.load(robot_config)
  robot_config = robot_config or config_lib.default(domain)
  if [m.name for m in robot_config.joints] != [
    j.name for j in task.robot.joints
  ]:
    raise config_lib.ConfigError(
      f'{robot_config.source}: its joints do not match the {domain} model'
    )
  # Motors measuring a model joint first: their readings map onto qpos.
  auxiliary_joints = dict(
    sorted(
      task.hardware_auxiliary_joints().items(), key=lambda item: item[1] is None
    )
  )
  auxiliary = []
  for name in auxiliary_joints:
    motor = robot_config.auxiliary_motor(name)
    if motor is None:
      raise config_lib.ConfigError(
        f'{robot_config.source}: {task_name} reads the {name} motor, which '
        'the configuration lacks'
      )
    auxiliary.append(motor)
  free_floating = task.root_joint is not None
  if tracker is not None:
    torso_source = tracker.torso_state
  virtual = device_path == VIRTUAL_DEVICE
  if free_floating and not virtual and torso_source is None:
    raise ValueError(
      f'{domain}/{task_name} needs the torso pose (upright, heading, '
      'position) from a motion tracker: pass tracker= (a '
      'robel_dm.hardware.tracking.TorsoTracker, e.g. on a NatNet stream; '
      "see docs/bringup.md), or use device_path='virtual' for the simulated "
      'bus.'
    )

  if reset is None:
    # ROBEL scripts the D'Claw's object tasks' reset. The D'Kitty's scripted
    # stand-up is opt-in: in simulation it gets up from a crouch but not
    # from lying on its back (see `resets.DKittyScriptedReset`).
    scripted = domain == 'dclaw' and auxiliary_joints
    reset = 'scripted' if scripted else 'move'
  if not free_floating:  # Checked before anything is opened.
    reset_procedure = resets.make(reset, robot_config, domain)
  on_close = [] if tracker is None else [tracker.close]
  if virtual:
    from robel_dm.hardware import sim_robot, virtual_bus  # noqa: PLC0415

    simulation = sim_robot.SimulatedRobot(
      domain, task_name, robot_config, task_kwargs=task_kwargs, seed=seed
    )
    servos = virtual_bus.make_servos(virtual_bus.robot_motor_ids(robot_config))
    bus = virtual_bus.Bus(servos, driver=simulation)
    server = virtual_bus.PtyBusServer(bus).start()
    on_close += [server.stop, simulation.close]
    device_path = server.device_path
    if free_floating and torso_source is None:
      torso_source = simulation.torso_pose
  if free_floating:
    reset_procedure = resets.make(reset, robot_config, domain, torso_source)
  motor_ids = [m.id for m in robot_config.joints + tuple(auxiliary)]
  client = dynamixel.DynamixelClient(
    device_path, motor_ids, baud_rate=robot_config.baud_rate
  )
  try:
    client.connect()
    robot = robot_lib.HardwareRobot(
      client, robot_config.joints, tuple(auxiliary)
    )
    if virtual:
      # Goals travel as broadcasts without a reply: a ping makes sure the
      # bus has applied them before the simulation advances.
      first = motor_ids[0]
      clock = clock_lib.SimulatedClock(
        simulation, before_advance=lambda: client.ping(first)
      )
    else:
      clock = clock_lib.WallClock()
    hardware = {
      'bus': bus if virtual else None,
      'simulation': simulation if virtual else None,
      'robot': robot,
      'auxiliary_joints': auxiliary_joints,
      'clock': clock,
      'torso_source': torso_source,
      'root_joint': task.root_joint,
      'joint_limits': robot_config.limits,
      'reset': reset_procedure,
      'tracker': tracker,
      'on_close': on_close,
    }
    _install_sigterm_handler()
    return HardwareEnvironment(task, hardware=hardware, **environment_kwargs)
  except BaseException:
    client.disconnect()
    for stop in on_close:
      stop()
    raise
