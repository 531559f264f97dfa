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
import dataclasses
import logging
import weakref

from dm_control import composer, mjcf

from robel_dm import environment as environment_lib
from robel_dm import robots
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


@dataclasses.dataclass(frozen=True)
class _RobotSetup:
  """What `make_environment` resolved and checked before opening anything.

  Attributes:
    robot_config: the motors' IDs and calibration.
    auxiliary_joints: auxiliary motor name -> the model joint it measures
      (None for the guide).
    auxiliary: the auxiliary motors, in the order of `auxiliary_joints`.
    guide: the guide motor's mode, or None.
    reset: the reset's name (or procedure), defaulted for the task.
    reset_procedure: a fixed robot's reset procedure; None for a
      free-floating one, whose reset needs the opened torso source.
    free_floating: whether the robot has a root joint (D'Kitty).
    virtual: whether the bus is the in-process virtual one.
  """

  robot_config: config_lib.RobotConfig
  auxiliary_joints: dict[str, object | None]
  auxiliary: tuple[config_lib.Motor, ...]
  guide: str | None
  reset: str | Callable[..., None]
  reset_procedure: Callable[..., None] | None
  free_floating: bool
  virtual: bool

  @property
  def motor_ids(self) -> list[int]:
    """The IDs of the joints' motors, then of the auxiliary ones."""
    return [m.id for m in self.robot_config.joints + self.auxiliary]


@dataclasses.dataclass
class _OpenedDevices:
  """The tracker and bus `make_environment` opened before the motors.

  Attributes:
    device_path: the serial device the motors' client connects to (the
      virtual bus's pty with device 'virtual').
    torso_source: a free-floating robot's torso pose, or None.
    tracker: the motion tracker, or None.
    on_close: stops what was opened, in order.
    bus: the in-process virtual bus, or None.
    simulation: the simulation behind the virtual bus, or None.
    bus_progress: the virtual bus server's (bytes in, bytes out), or None.
  """

  device_path: str
  torso_source: connection_lib.TorsoSource | None
  tracker: object | None
  on_close: list[Callable[[], None]]
  bus: object | None = None
  simulation: object | None = None
  bus_progress: Callable[[], tuple[int, int]] | None = None


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
  setup = _resolve_setup(task, domain, robot, scene_factory, torso_source)
  opened = _open_devices(setup, robot, scene_factory, torso_source)
  reset_procedure = setup.reset_procedure
  if setup.free_floating:
    # On the simulated robot a manual reset's person is simulated too.
    reset_procedure = resets.make(
      setup.reset,
      setup.robot_config,
      domain,
      opened.torso_source,
      operator=opened.simulation.place_at_start if setup.virtual else None,
    )
  client = dynamixel.DynamixelClient(
    opened.device_path,
    setup.motor_ids,
    baud_rate=setup.robot_config.baud_rate,
    bus_progress=opened.bus_progress,
  )
  try:
    client.connect()
    connection = _make_connection(client, setup, opened, reset_procedure)
    shutdown.install_exit_signals()
    return HardwareEnvironment(
      task, connection=connection, **environment_kwargs
    )
  except BaseException:
    client.disconnect()
    for stop in opened.on_close:
      stop()
    raise


def _resolve_setup(
  task: composer.Task,
  domain: str,
  robot: options_lib.RobotOptions,
  scene_factory: SceneFactory | None,
  torso_source: connection_lib.TorsoSource | None,
) -> _RobotSetup:
  """Loads the robot configuration, picks the reset and checks that the
  task can run on this setup, all before anything is opened."""
  robot_config = robot.robot_config
  if isinstance(robot_config, str):
    robot_config = config_lib.load(robot_config)
  robot_config = robot_config or config_lib.default(domain)
  task_label = f'{domain} task {type(task).__name__}'
  if robot_config.robot != domain:
    raise config_lib.ConfigError(
      f'{robot_config.source}: a {robot_config.robot} configuration, for a '
      f'{domain} task'
    )
  if [m.name for m in robot_config.joints] != [
    j.name for j in task.robot.joints
  ]:
    raise config_lib.ConfigError(
      f'{robot_config.source}: its joints do not match the {domain} model'
    )
  auxiliary_joints, auxiliary = _auxiliary_motors(
    task, robot_config, robot.guide, task_label
  )
  free_floating = task.root_joint is not None
  virtual = robot.virtual
  if virtual and scene_factory is None:
    raise ValueError(
      "device_path='virtual' needs a scene_factory that builds the simulated "
      'robot (suite.load passes one)'
    )
  # A tracker spec was checked when `robot` was built: it opens later.
  if torso_source is not None and robot.tracker is not None:
    raise ValueError(
      'give the torso pose by torso_source or by a tracker, not both'
    )
  has_torso = torso_source is not None or robot.tracker is not None
  if has_torso and not free_floating:
    raise ValueError(
      f'the {task_label} has no free torso: a tracker or torso_source has '
      'nothing to track'
    )
  if free_floating and not virtual and not has_torso:
    raise ValueError(
      f'the {task_label} needs the torso pose (upright, heading, '
      'position) from a motion tracker: pass tracker= (a robel_dm.'
      'hardware.tracking.tracker.TorsoTracker, e.g. on a NatNet stream; '
      "see docs/bringup.md), or use device_path='virtual' for the simulated "
      'bus.'
    )
  reset = robot.reset
  if reset is None:
    reset = _default_reset(task, domain)
  return _RobotSetup(
    robot_config=robot_config,
    auxiliary_joints=auxiliary_joints,
    auxiliary=auxiliary,
    guide=robot.guide,
    reset=reset,
    # A free-floating robot's reset needs the torso source opened later.
    reset_procedure=(
      None if free_floating else resets.make(reset, robot_config, domain)
    ),
    free_floating=free_floating,
    virtual=virtual,
  )


def _auxiliary_motors(
  task: composer.Task,
  robot_config: config_lib.RobotConfig,
  guide: str | None,
  task_label: str,
) -> tuple[dict[str, object | None], tuple[config_lib.Motor, ...]]:
  """The auxiliary motors the task (and the guide) read: name -> the model
  joint each measures, and the motors in that order."""
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
  return auxiliary_joints, tuple(auxiliary)


def _default_reset(task: composer.Task, domain: str) -> str:
  """The reset a task gets when none is asked for."""
  # ROBEL scripts the D'Claw's object tasks' reset. The D'Kitty's scripted
  # stand-up is opt-in: in simulation it gets up from a crouch but not
  # from lying on its back (see `resets.DKittyScriptedReset`).
  scripted = (
    robots.ROBOTS[domain].scripted_reset_with_object and task.auxiliary_joints()
  )
  return 'scripted' if scripted else 'move'


def _open_devices(
  setup: _RobotSetup,
  robot: options_lib.RobotOptions,
  scene_factory: SceneFactory | None,
  torso_source: connection_lib.TorsoSource | None,
) -> _OpenedDevices:
  """Opens the tracker, then (device 'virtual') the simulation and its
  virtual bus behind a pty; a real port is opened by the client later."""
  tracker = robot.tracker
  if isinstance(tracker, str):
    tracker = tracker_spec.make_tracker(tracker)
  if tracker is not None:
    torso_source = tracker.torso_state
  opened = _OpenedDevices(
    device_path=robot.device_path,
    torso_source=torso_source,
    tracker=tracker,
    on_close=[] if tracker is None else [tracker.close],
  )
  if setup.virtual:
    _open_virtual_bus(opened, setup, scene_factory)
  return opened


def _open_virtual_bus(
  opened: _OpenedDevices, setup: _RobotSetup, scene_factory: SceneFactory
) -> None:
  """Starts the simulation and its virtual bus on a pty, recording them
  (and how to stop them) in `opened`."""
  from robel_dm.hardware import virtual as virtual_lib  # noqa: PLC0415
  from robel_dm.hardware.virtual import sim_robot  # noqa: PLC0415

  robot_config = setup.robot_config
  simulation = sim_robot.SimulatedRobot(scene_factory(), robot_config)
  servos = virtual_lib.make_servos(virtual_lib.robot_motor_ids(robot_config))
  bus = virtual_lib.Bus(servos, driver=simulation)
  server = virtual_lib.PtyBusServer(bus).start()
  opened.on_close += [server.stop, simulation.close]
  opened.device_path = server.device_path
  opened.bus, opened.simulation = bus, simulation
  # The simulated bus answers from a thread here: the client waits for it
  # when busy. (bytes_in is counted after the reply is sent, so read it
  # first.)
  opened.bus_progress = lambda: (
    server.stats['bytes_in'],
    server.stats['bytes_out'],
  )
  if setup.free_floating and opened.torso_source is None:
    opened.torso_source = simulation.torso_pose


def _make_connection(
  client: dynamixel.DynamixelClient,
  setup: _RobotSetup,
  opened: _OpenedDevices,
  reset_procedure: Callable[..., None],
) -> connection_lib.Connection:
  """The connection of a connected client's robot with its clock."""
  robot_config = setup.robot_config
  robot = robot_lib.HardwareRobot(
    client, robot_config.joints, setup.auxiliary, robot_config.health
  )
  if setup.virtual:
    clock = _simulated_clock(client, opened.simulation, setup.motor_ids[0])
  else:
    clock = clock_lib.WallClock()
  return connection_lib.Connection(
    robot=robot,
    robot_config=robot_config,
    clock=clock,
    auxiliary_joints=setup.auxiliary_joints,
    joint_limits=robot_config.limits,
    reset=reset_procedure,
    torso_source=opened.torso_source,
    tracker=opened.tracker,
    guide=setup.guide,
    bus=opened.bus,
    simulation=opened.simulation,
    on_close=opened.on_close,
  )


def _simulated_clock(
  client: dynamixel.DynamixelClient, simulation, first_motor: int
) -> clock_lib.SimulatedClock:
  """The simulation's clock, which syncs with the bus before advancing."""

  def sync_with_bus() -> None:
    # Goals travel as broadcasts without a reply: a ping makes sure the
    # bus has applied them before the simulation advances. A silent bus
    # is for the state read that follows to diagnose.
    with contextlib.suppress(dynamixel.MissingMotorError):
      client.ping(first_motor, attempts=1)

  return clock_lib.SimulatedClock(simulation, before_advance=sync_with_bus)
