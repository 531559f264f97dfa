"""The virtual bus's command line: a robot's motors on a pseudo-terminal.

  robel-virtual-bus --robot=dclaw

prints the device path of a pseudo-terminal on which a virtual servo bus
serves every motor of the robot's shipped configuration (or of `--config`),
then serves it until SIGINT or SIGTERM. `--driver=sim` (the default) moves
the motors with a MuJoCo simulation of the robot in real time;
`--driver=ideal` puts every motor at its goal at once. The bus publishes
on its pty how much it has answered, so that a robel_dm client (any
`DynamixelClient`) waits for it while a busy machine holds it up, and calls
a motor silent only once it has answered; another client (the bare SDK)
has the SDK's ~34 ms reply deadline, which a loaded machine can miss.

`build_bus` assembles such a bus from a configuration and the name of a
driver (`DRIVERS`).
"""

from collections.abc import Callable, Sequence
import logging
import math
import signal
import sys

from robel_dm import robots
from robel_dm.hardware import config
from robel_dm.hardware.virtual import registers
from robel_dm.hardware.virtual.bus import (
  Bus,
  Driver,
  IdealDriver,
  robot_motor_ids,
)
from robel_dm.hardware.virtual.servo import DEFAULT_MODEL_NUMBER, make_servos
from robel_dm.hardware.virtual.transport import PtyBusServer

# --driver values: factories of a driver for a robot configuration and a
# calibration file of the simulated robot (or None).
DriverFactory = Callable[[config.RobotConfig, str | None], Driver]


def _simulated_robot(
  robot_config: config.RobotConfig, dynamics: str | None
) -> Driver:
  # Imported here: they need MuJoCo, and the command line builds the scene.
  from robel_dm import suite  # noqa: PLC0415
  from robel_dm.hardware.virtual import sim_robot  # noqa: PLC0415

  scene = suite.load(
    robot_config.robot,
    robots.ROBOTS[robot_config.robot].standalone_scene,
    seed=0,
    time_limit=math.inf,
    dynamics=dynamics,
  )
  return sim_robot.SimulatedRobot(scene, robot_config, realtime=True)


DRIVERS: dict[str, DriverFactory] = {
  'ideal': lambda robot_config, dynamics: IdealDriver(),
  # A MuJoCo simulation of the robot, advancing with the wall clock.
  'sim': _simulated_robot,
}


def build_bus(
  robot_config: config.RobotConfig,
  driver: str = 'ideal',
  model_number: int = DEFAULT_MODEL_NUMBER,
  dynamics: str | None = None,
) -> Bus:
  """A bus with one servo per motor of `robot_config`.

  Args:
    robot_config: the robot.
    driver: a key of DRIVERS.
    model_number: the servos' model.
    dynamics: with driver 'sim', a calibration file of the simulated robot
      (`robel_dm.calibration`): its gains, damping, friction, armature and
      control delay; ROBEL's model if None.

  Raises:
    ValueError: for an unknown driver.
  """
  if driver not in DRIVERS:
    raise ValueError(f'unknown driver {driver!r}; known: {sorted(DRIVERS)}')
  servos = make_servos(robot_motor_ids(robot_config), model_number)
  if dynamics is not None and driver != 'sim':
    raise ValueError(f'dynamics needs the sim driver, not {driver!r}')
  return Bus(servos, driver=DRIVERS[driver](robot_config, dynamics))


def _define_flags():
  from absl import flags  # Command line only.

  return {
    'robot': flags.DEFINE_enum(
      'robot',
      'dclaw',
      sorted(robots.ROBOTS),
      'Robot whose shipped configuration to serve.',
    ),
    'config': flags.DEFINE_string(
      'config', None, 'Robot configuration file (JSON); overrides --robot.'
    ),
    'driver': flags.DEFINE_enum(
      'driver',
      'sim',
      sorted(DRIVERS),
      'What moves the motors: sim (a MuJoCo simulation of the robot, in real '
      'time) or ideal (every motor at its goal at once).',
    ),
    'model_number': flags.DEFINE_enum(
      'model_number',
      str(DEFAULT_MODEL_NUMBER),
      [str(number) for number in registers.MODEL_DEFAULTS],
      "Model number of every servo (1040: XH430-V350, ROBEL's).",
    ),
    'dynamics': flags.DEFINE_string(
      'dynamics',
      None,
      'Calibration file of the simulated robot (robel_dm.calibration): '
      'another robot of the same design.',
    ),
  }


def _serve_until_signalled(flag_values) -> int:
  # SIGINT and SIGTERM wait, blocked in this thread and in the server's
  # (which inherits the mask), until `sigwait` takes one: a handler could
  # interrupt the very lock it needs, and one arriving while the scene loads
  # ends the program cleanly once it has.
  stop_signals = {signal.SIGINT, signal.SIGTERM}
  signal.pthread_sigmask(signal.SIG_BLOCK, stop_signals)
  try:
    if flag_values['config'].value:
      robot_config = config.load(flag_values['config'].value)
    else:
      robot_config = config.default(flag_values['robot'].value)
  except config.ConfigError as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  try:
    bus = build_bus(
      robot_config,
      flag_values['driver'].value,
      int(flag_values['model_number'].value),
      flag_values['dynamics'].value,
    )
  except (ValueError, OSError) as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  with PtyBusServer(bus) as server:
    print(server.device_path, flush=True)
    logging.info(
      'serving %s motors %s on %s',
      robot_config.robot,
      robot_motor_ids(robot_config),
      server.device_path,
    )
    signal.sigwait(stop_signals)
  return 0


def main(argv: Sequence[str] | None = None) -> None:
  """Serves a robot's motors until SIGINT or SIGTERM."""
  from absl import app  # Command line only.

  from robel_dm import command_help  # noqa: PLC0415 (imports absl)

  flag_values = _define_flags()
  command_help.set_help(__doc__, __name__)

  def run(args: Sequence[str]) -> int:
    if len(args) > 1:
      raise app.UsageError(f'unexpected arguments: {args[1:]}')
    return _serve_until_signalled(flag_values)

  app.run(run, argv=argv)


if __name__ == '__main__':
  main()
