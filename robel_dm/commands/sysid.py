r"""System identification from the command line.

  python -m robel_dm.sysid excite --domain=dclaw --device_path=DEVICE \
      --record=DIR [--signal=steps|chirp] [--duration=10] [--episodes=1]
  python -m robel_dm.sysid fit DIR [DIR ...] --domain=dclaw \
      --output=calibration.json [--parameters=kp,damping,...]

`excite` drives the robot through an excitation sequence and records it;
`fit` fits the simulated robot to recordings, prints the per-joint error
before and after and a warning line for each poorly determined value, and
writes the calibration that `suite.load(...,
dynamics=FILE)` and `evaluate --dynamics=FILE` apply. See docs/sysid.md.
"""

import sys

from absl import app, flags
import numpy as np

from robel_dm import calibration, commands, provenance, recording, suite
from robel_dm.sysid import excite as excite_lib
from robel_dm.sysid import fit as fit_lib
from robel_dm.tasks import excitation

FLAGS = flags.FLAGS
COMMANDS = ('excite', 'fit')


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


def _robot() -> suite.RobotOptions | None:
  if not FLAGS.device_path:
    if FLAGS.robot_config:
      raise ValueError('--robot_config needs --device_path (a robot)')
    return None
  return suite.RobotOptions(FLAGS.device_path, robot_config=FLAGS.robot_config)


def excite() -> int:
  if not FLAGS.record:
    raise ValueError('excite needs --record=DIR (where the episodes go)')
  excitation = excite_lib.Excitation(
    signal=FLAGS.signal,
    duration=FLAGS.duration,
    amplitude=FLAGS.amplitude,
    joints=tuple(FLAGS.joints) if FLAGS.joints else None,
    seed=FLAGS.seed,
  )
  env = suite.load_excitation(
    FLAGS.domain,
    FLAGS.duration,
    seed=FLAGS.seed,
    robot=_robot(),
    dynamics=FLAGS.dynamics,
  )
  metadata = {
    'kind': 'excitation',
    'domain': FLAGS.domain,
    'excitation': excitation.to_dict(),
    'device_path': FLAGS.device_path,
    'dynamics': FLAGS.dynamics,
  }
  try:
    # The recorder checks the directory before the robot moves.
    env = recording.Recorder(env, FLAGS.record, metadata=metadata)
    steps = excite_lib.run(env, excitation, FLAGS.episodes)
  finally:
    env.close()
  print(f'recorded {FLAGS.episodes} episodes, {steps} steps in {FLAGS.record}')
  return 0


def fit(directories: list[str]) -> int:
  if not directories:
    raise ValueError('fit needs the recording directories to fit')
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
  print(report(result))
  if FLAGS.output:
    calibration.save(result.calibration, FLAGS.output)
    print(f'wrote {FLAGS.output}')
  return 0


def _cell(result: fit_lib.FitResult, joint: int, parameter: str) -> str:
  """A fitted value, '?' if not identified, and its ratio to the model's."""
  value = result.fitted[parameter][joint]
  name = f'{result.joint_names[joint]}.{parameter}'
  flag = '?' if name in result.not_identified else ' '
  nominal = result.nominal[parameter][joint]
  if nominal <= 0:  # No ratio to a model value of zero (friction loss).
    return f'{value:>13.4g}{flag}'
  return f'{value:>10.4g}{flag}{value / nominal:>3.1f}x'


def report(result: fit_lib.FitResult) -> str:
  """The fit as a table: per joint, the values and the angle error."""
  names = list(result.fitted)
  header = f'{"joint":<8}' + ''.join(f'{n:>14}' for n in names)
  header += f'{"RMS error (deg): model":>26}{"fit":>8}'
  lines = [header]
  for j, joint in enumerate(result.joint_names):
    cells = ''.join(_cell(result, j, n) for n in names)
    before, after = np.degrees([result.rms_before[j], result.rms_after[j]])
    lines.append(f'{joint:<8}{cells}{before:>26.3f}{after:>8.3f}')
  lines.append(
    f'control delay {result.control_delay * 1e3:.1f} ms; RMS angle error '
    f'{np.degrees(np.sqrt(np.mean(result.rms_before**2))):.3f} -> '
    f'{np.degrees(np.sqrt(np.mean(result.rms_after**2))):.3f} deg; '
    f'{result.evaluations} simulations'
  )
  lines += warning_lines(result)
  return '\n'.join(lines)


def warning_lines(result: fit_lib.FitResult) -> list[str]:
  """One line per poorly determined value (marked '?' in the table)."""
  lines = []
  for name, reason in result.poorly_determined.items():
    joint, parameter = name.split('.')
    j = result.joint_names.index(joint)
    value = result.fitted[parameter][j]
    error = result.standard_error[parameter][j]
    lines.append(
      f'? warning: {name} = {value:.4g} +- {error:.2g} (standard error) is '
      f'poorly determined: {reason}'
    )
  return lines


def main(argv: list[str]) -> int:
  if len(argv) < 2 or argv[1] not in COMMANDS:
    raise app.UsageError(f'the first argument must be one of {COMMANDS}')
  command, rest = argv[1], argv[2:]
  try:
    if command == 'excite':
      if rest:
        raise app.UsageError(f'unexpected arguments: {rest}')
      return excite()
    return fit(rest)
  except (ValueError, RuntimeError, ImportError) as error:
    # Includes calibration, recording and robot errors, and a missing extra
    # (named); a robot's motors were released on the way out (see
    # robel_dm.hardware.shutdown).
    print(f'error: {error}', file=sys.stderr)
    return 2
  except KeyboardInterrupt:
    print('interrupted', file=sys.stderr)
    return 130


def run() -> None:
  """The command (`robel-sysid`, or `python -m robel_dm.sysid`)."""
  _define_flags()
  commands.describe(__doc__, __name__)
  app.run(main)


if __name__ == '__main__':
  run()
