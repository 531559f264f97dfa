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

from collections.abc import Callable
import contextlib
import logging
import weakref

from dm_control import composer, mjcf

from robel_dm import constants, robots
from robel_dm import environment as environment_lib
from robel_dm.hardware import clock as clock_lib
from robel_dm.hardware import config as config_lib
from robel_dm.hardware import connection as connection_lib
from robel_dm.hardware import options as options_lib
from robel_dm.hardware import physics as physics_lib
from robel_dm.hardware import resets, shutdown
from robel_dm.hardware import robot as robot_lib
from robel_dm.hardware import robot_io as robot_io_lib
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.tracking import spec as tracker_spec

VIRTUAL_DEVICE = constants.VIRTUAL_DEVICE

# Builds the simulated environment a virtual bus's motors follow.
SceneFactory = Callable[[], composer.Environment]


class HardwareEnvironment(environment_lib.Environment):
  """A robel_dm environment on motors; see `make_environment`."""

  def __init__(
    self,
    task: composer.Task,
    *,
    connection: connection_lib.Connection,
    **kwargs,
  ):
    self._connection = connection
    # Releases the robot once: on close, or when the environment is
    # garbage-collected without being closed (and at exit, at the latest).
    self._release = weakref.finalize(self, _disconnect, connection)
    super().__init__(task, physics_factory=self._make_physics, **kwargs)

  @property
  def robot(self) -> robot_lib.HardwareRobot:
    return self._connection.robot

  @property
  def robot_config(self) -> config_lib.RobotConfig:
    """The motors' IDs and calibration."""
    return self._connection.robot_config

  @property
  def virtual_bus(self):
    """The in-process virtual bus (device 'virtual'), else None."""
    return self._connection.bus

  @property
  def simulated_robot(self):
    """The simulation behind the virtual bus (device 'virtual'), else None."""
    return self._connection.simulation

  def _make_physics(
    self, mjcf_model: mjcf.RootElement
  ) -> physics_lib.HardwarePhysics:
    connection, task = self._connection, self.task
    physics = physics_lib.HardwarePhysics.from_mjcf_model(mjcf_model)
    physics.attach(
      connection,
      joints=task.robot.joints,
      actuators=task.robot.actuators,
      control_timestep=task.control_timestep,
      root_joint=task.root_joint,
    )
    task.use_robot_io(
      robot_io_lib.HardwareRobotIO(
        physics, tracker=connection.tracker, guide=connection.guide
      )
    )
    return physics

  def close(self) -> None:
    """Releases the motors, closes the port (and the virtual bus)."""
    try:
      self._release()
    finally:
      super().close()

  def __enter__(self) -> 'HardwareEnvironment':
    return self

  def __exit__(self, *exc_info) -> None:
    self.close()


def _disconnect(connection: connection_lib.Connection) -> None:
  """Releases the motors and closes the port, then whatever else the
  connection opened (the virtual bus, a tracker), each whatever the others
  raise. A forked child's copy closes nothing: its owner does."""
  if not connection.robot.in_owner_process:
    return
  try:
    connection.robot.client.disconnect()
  finally:
    for stop in connection.on_close:
      try:
        stop()
      except Exception as error:  # noqa: BLE001 (stop every part)
        logging.error('closing %r failed: %r', stop, error)


def make_environment(
  task: composer.Task,
  *,
  domain: str,
  robot: options_lib.RobotOptions,
  scene_factory: SceneFactory | None = None,
  torso_source: connection_lib.TorsoSource | None = None,
  **environment_kwargs,
) -> HardwareEnvironment:
  """Connects `task` to a robot.

  Args:
    task: the task (built as for simulation).
    domain: 'dclaw' or 'dkitty'.
    robot: the robot and how to run on it: device, configuration, reset,
      guide motor, tracker (see `options.RobotOptions`).
    scene_factory: with device 'virtual': builds the simulated environment
      whose robot the virtual bus's motors follow (the simulation owns and
      closes it).
    torso_source: for a free-floating robot (D'Kitty) on a real bus: a
      callable returning the torso's (position, quaternion, linear
      velocity, angular velocity in the torso frame).
    **environment_kwargs: forwarded to the environment.

  Returns:
    The environment; close it (or use it as a context manager).

  Raises:
    config_lib.ConfigError: for a malformed configuration.
    dynamixel.DynamixelError: if the port or a motor is not there.
    ValueError: if the task needs a sensor this robot setup lacks, or for a
      guide the task cannot use.
  """
  device_path, reset, guide = robot.device_path, robot.reset, robot.guide
  tracker = robot.tracker  # A spec was checked when `robot` was built.
  robot_config = robot.robot_config
  if isinstance(robot_config, str):
    robot_config = config_lib.load(robot_config)
  robot_config = robot_config or config_lib.default(domain)
  task_label = f'{domain} task {type(task).__name__}'
  if [m.name for m in robot_config.joints] != [
    j.name for j in task.robot.joints
  ]:
    raise config_lib.ConfigError(
      f'{robot_config.source}: its joints do not match the {domain} model'
    )
  auxiliary_joints = dict(task.auxiliary_joints())
  if guide is not None:
    if not task.goal_is_an_angle:
      raise ValueError(
        f'guide={guide!r}: the {task_label} has no goal angle to show or set'
      )
    # The guide measures no model joint: it comes after those that do.
    auxiliary_joints[robot_io_lib.GUIDE_MOTOR] = None
  auxiliary = []
  for name in auxiliary_joints:
    motor = robot_config.auxiliary_motor(name)
    if motor is None:
      raise config_lib.ConfigError(
        f'{robot_config.source}: the {task_label} reads the {name} motor, '
        'which the configuration lacks'
      )
    auxiliary.append(motor)
  free_floating = task.root_joint is not None
  virtual = device_path == VIRTUAL_DEVICE
  if virtual and scene_factory is None:
    raise ValueError(
      "device_path='virtual' needs a scene_factory that builds the simulated "
      'robot (suite.load passes one)'
    )
  if free_floating and not virtual and torso_source is None and tracker is None:
    raise ValueError(
      f'the {task_label} needs the torso pose (upright, heading, '
      'position) from a motion tracker: pass tracker= (a robel_dm.'
      'hardware.tracking.tracker.TorsoTracker, e.g. on a NatNet stream; '
      "see docs/bringup.md), or use device_path='virtual' for the simulated "
      'bus.'
    )

  if reset is None:
    # ROBEL scripts the D'Claw's object tasks' reset. The D'Kitty's scripted
    # stand-up is opt-in: in simulation it gets up from a crouch but not
    # from lying on its back (see `resets.DKittyScriptedReset`).
    scripted = (
      robots.ROBOTS[domain].scripted_reset_with_object
      and task.auxiliary_joints()
    )
    reset = 'scripted' if scripted else 'move'
  if not free_floating:  # Checked before anything is opened.
    reset_procedure = resets.make(reset, robot_config, domain)
  if isinstance(tracker, str):
    tracker = tracker_spec.make_tracker(tracker)
  if tracker is not None:
    torso_source = tracker.torso_state
  on_close = [] if tracker is None else [tracker.close]
  bus = simulation = None
  if virtual:
    from robel_dm.hardware import virtual as virtual_lib  # noqa: PLC0415
    from robel_dm.hardware.virtual import sim_robot  # noqa: PLC0415

    simulation = sim_robot.SimulatedRobot(scene_factory(), robot_config)
    servos = virtual_lib.make_servos(virtual_lib.robot_motor_ids(robot_config))
    bus = virtual_lib.Bus(servos, driver=simulation)
    server = virtual_lib.PtyBusServer(bus).start()
    on_close += [server.stop, simulation.close]
    device_path = server.device_path
    if free_floating and torso_source is None:
      torso_source = simulation.torso_pose
  if free_floating:
    # On the simulated robot a manual reset's person is simulated too.
    reset_procedure = resets.make(
      reset,
      robot_config,
      domain,
      torso_source,
      operator=simulation.place_at_start if virtual else None,
    )
  motor_ids = [m.id for m in robot_config.joints + tuple(auxiliary)]
  client = dynamixel.DynamixelClient(
    device_path,
    motor_ids,
    baud_rate=robot_config.baud_rate,
    # The simulated bus answers from a thread here: wait for it when busy.
    # (bytes_in is counted after the reply is sent, so read it first.)
    bus_progress=(
      (lambda: (server.stats['bytes_in'], server.stats['bytes_out']))
      if virtual
      else None
    ),
  )
  try:
    client.connect()
    robot = robot_lib.HardwareRobot(
      client, robot_config.joints, tuple(auxiliary)
    )
    if virtual:
      first = motor_ids[0]

      def sync_with_bus() -> None:
        # Goals travel as broadcasts without a reply: a ping makes sure the
        # bus has applied them before the simulation advances. A silent bus
        # is for the state read that follows to diagnose.
        with contextlib.suppress(dynamixel.MissingMotorError):
          client.ping(first, attempts=1)

      clock = clock_lib.SimulatedClock(simulation, before_advance=sync_with_bus)
    else:
      clock = clock_lib.WallClock()
    connection = connection_lib.Connection(
      robot=robot,
      robot_config=robot_config,
      clock=clock,
      auxiliary_joints=auxiliary_joints,
      joint_limits=robot_config.limits,
      reset=reset_procedure,
      torso_source=torso_source,
      tracker=tracker,
      guide=guide,
      bus=bus,
      simulation=simulation,
      on_close=on_close,
    )
    shutdown.install_exit_signals()
    return HardwareEnvironment(
      task, connection=connection, **environment_kwargs
    )
  except BaseException:
    client.disconnect()
    for stop in on_close:
      stop()
    raise
