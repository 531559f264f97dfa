r"""System identification from the command line.

  robel-sysid excite --domain=dclaw --device_path=DEVICE \
      --record=DIR [--signal=steps|chirp] [--duration=10] [--episodes=1]
  robel-sysid fit DIR [DIR ...] --domain=dclaw \
      --output=calibration.json [--parameters=kp,damping,...]

`excite` drives the robot through an excitation sequence and records it;
`fit` fits the simulated robot to recordings, prints the per-joint error
before and after and a warning line for each poorly determined value, and
writes the calibration that `suite.load(...,
dynamics=FILE)` and `robel-evaluate --dynamics=FILE` apply. See docs/sysid.md.
"""

import sys

from absl import app, flags

from robel_dm import calibration, command_help, provenance, recording, suite
from robel_dm.evaluation import checks, cli
from robel_dm.sysid import excite as excite_lib
from robel_dm.sysid import fit as fit_lib
from robel_dm.sysid import report
from robel_dm.tasks import excitation

FLAGS = flags.FLAGS
COMMANDS = ('excite', 'fit')
# The flags each command reads (besides --domain); given to the other one,
# a flag is refused rather than ignored.
_FLAGS_OF = {
  'excite': ('device_path', 'robot_config', 'dynamics', 'record', 'signal',
             'duration', 'episodes', 'amplitude', 'joints', 'seed'),
  'fit': ('output', 'parameters', 'fit_delay', 'currents'),
}  # fmt: skip


def _define_flags() -> None:
  flags.DEFINE_enum('domain', 'dclaw', list(excitation.DOMAINS), 'The robot.')
  flags.DEFINE_string(
    'device_path', None,
    "excite: the robot's Dynamixel bus, or 'virtual' for the simulated bus; "
    'unset simulates.',
  )  # fmt: skip
  flags.DEFINE_string(
    'robot_config', None, 'excite: the robot configuration (JSON).'
  )
  flags.DEFINE_string(
    'dynamics', None,
    'excite: a calibration of the simulated robot (simulation or the '
    'virtual bus only).',
  )  # fmt: skip
  flags.DEFINE_string('record', None, 'excite: the recording directory.')
  flags.DEFINE_enum('signal', 'steps', list(excite_lib.SIGNALS), 'excite.')
  flags.DEFINE_float('duration', 10.0, 'excite: seconds per episode.')
  flags.DEFINE_integer('episodes', 1, 'excite: episodes.', lower_bound=1)
  flags.DEFINE_float(
    'amplitude', 0.4,
    "excite: fraction of each joint's half action range to move.",
  )  # fmt: skip
  flags.DEFINE_list('joints', None, 'excite: joints to move (default all).')
  flags.DEFINE_integer('seed', 0, 'excite: seed of the sequence.')
  flags.DEFINE_string('output', None, 'fit: write the calibration here.')
  flags.DEFINE_list(
    'parameters', list(calibration.PARAMETERS), 'fit: parameters to fit.'
  )
  flags.DEFINE_bool('fit_delay', True, 'fit: also fit the control delay.')
  flags.DEFINE_bool(
    'currents', True, 'fit: also fit measured motor currents (robots only).'
  )


def excite() -> int:
  if not FLAGS.record:
    raise ValueError('excite needs --record=DIR (where the episodes go)')
  sequence = excite_lib.Excitation(
    signal=FLAGS.signal,
    duration=FLAGS.duration,
    amplitude=FLAGS.amplitude,
    joints=tuple(FLAGS.joints) if FLAGS.joints else None,
    seed=FLAGS.seed,
  )
  # The joints are checked before the robot is opened.
  excite_lib.check_joints(sequence, excitation.JOINT_NAMES[FLAGS.domain])
  env = suite.load_excitation(
    FLAGS.domain,
    FLAGS.duration,
    seed=FLAGS.seed,
    robot=cli.robot_options(FLAGS, names=('robot_config',)),
    dynamics=FLAGS.dynamics,
  )
  metadata = {
    'kind': 'excitation',
    'domain': FLAGS.domain,
    'excitation': sequence.to_dict(),
    'device_path': FLAGS.device_path,
    'dynamics': FLAGS.dynamics,
  }
  try:
    # The recorder checks the directory before the robot moves.
    env = recording.Recorder(env, FLAGS.record, metadata=metadata)
    steps = excite_lib.run(env, sequence, FLAGS.episodes)
  finally:
    env.close()
  print(f'recorded {FLAGS.episodes} episodes, {steps} steps in {FLAGS.record}')
  return 0


def _check_flags_of(command: str) -> None:
  """Raises ValueError for a flag of the other command."""
  for other, names in _FLAGS_OF.items():
    given = [name for name in names if FLAGS[name].present]
    if other != command and given:
      raise ValueError(f'--{given[0]} is a flag of {other}, not of {command}')


def fit(directories: list[str]) -> int:
  if not directories:
    raise ValueError('fit needs the recording directories to fit')
  checks.check_output(FLAGS.output)  # Before minutes of fitting.
  trajectories = []
  for directory in directories:
    trajectories += fit_lib.load_trajectories(directory, FLAGS.domain)
  result = fit_lib.fit(
    trajectories,
    FLAGS.domain,
    parameters=tuple(FLAGS.parameters),
    fit_delay=FLAGS.fit_delay,
    use_currents=FLAGS.currents,
    source={'recordings': directories, 'provenance': provenance.describe()},
  )
  print(report.fit_table(result))
  if FLAGS.output:
    calibration.save(result.calibration, FLAGS.output)
    print(f'wrote {FLAGS.output}')
  else:
    print('calibration not written (no --output)')
  return 0


def main(argv: list[str]) -> int:
  if len(argv) < 2 or argv[1] not in COMMANDS:
    raise app.UsageError(f'the first argument must be one of {COMMANDS}')
  command, rest = argv[1], argv[2:]
  try:
    _check_flags_of(command)
    if command == 'excite':
      if rest:
        raise app.UsageError(f'unexpected arguments: {rest}')
      return excite()
    return fit(rest)
  except (ValueError, RuntimeError, ImportError, OSError) as error:
    # Includes calibration, recording and robot errors, and a missing extra
    # (named); a robot's motors were released on the way out (see
    # robel_dm.hardware.shutdown).
    print(f'error: {error}', file=sys.stderr)
    return 2
  except KeyboardInterrupt:
    print('interrupted', file=sys.stderr)
    return 130


def run() -> None:
  """The command (`robel-sysid`, or `python -m robel_dm.commands.sysid`)."""
  command_help.run_absl(_define_flags, main, __doc__, __name__)


if __name__ == '__main__':
  run()
