r"""A Stable-Baselines3 model as a `policy.npz` that `robel-evaluate` runs.

    robel-convert --model=model.zip --algo=sac \
        --domain=dclaw --task=pose_fixed --output=policy.npz

`--algo` is `sac` (stable_baselines3.SAC), `tqc` (sb3_contrib.TQC) or `ppo`
(stable_baselines3.PPO); the model must have been trained on the task's
Gymnasium environment. Before anything is written the conversion checks
the model's algo, its observation and action spaces and that the numpy
policy gives the model's deterministic actions (`robel_dm.learning.convert`
says how). Any failure is one line and exit status 2. Needs the `learn`
extra and the model's library.
"""

import argparse
from collections.abc import Sequence
import sys

from robel_dm.evaluation import checks, task_args
from robel_dm.learning import convert


class _Parser(argparse.ArgumentParser):
  def error(self, message: str):  # One line, not argparse's usage too.
    print(f'error: {message}', file=sys.stderr)
    sys.exit(2)


def main(argv: Sequence[str] | None = None) -> int:
  """The command (`robel-convert`); returns the exit status (2: not
  converted)."""
  parser = _Parser(description=__doc__.splitlines()[0])
  parser.add_argument('--model', required=True, help='the SB3 model .zip')
  parser.add_argument('--algo', required=True, help=', '.join(convert.ALGOS))
  parser.add_argument('--domain', required=True, help='dclaw or dkitty')
  parser.add_argument('--task', required=True, help='e.g. pose_fixed')
  parser.add_argument('--task_kwargs', default='', help='e.g. valve=valve4')
  parser.add_argument('--output', required=True, help='the policy.npz')
  args = parser.parse_args(argv)
  try:
    if not args.output.endswith('.npz'):
      raise ValueError(f'--output: {args.output} must end in .npz')
    checks.check_output(args.output)
    policy = convert.convert(
      args.model,
      args.algo,
      args.domain,
      args.task,
      task_args.parse_task_kwargs(args.task_kwargs),
    )
    convert.save(policy, args.output)
  except (ValueError, OSError, ImportError) as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  checked = policy.metadata['checked']
  print(
    f"wrote {args.output}: the model's actions on "
    f'{checked["observations"]} observations, within '
    f'{checked["max_difference"]:.2g}'
  )
  return 0


if __name__ == '__main__':
  sys.exit(main())
