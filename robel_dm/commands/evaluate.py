"""The evaluation command: `robel-evaluate` (or
`python -m robel_dm.commands.evaluate`).

Evaluates a policy on robel_dm tasks and reports ROBEL's metrics; its flags
and main are `robel_dm.evaluation.cli`'s, its description `cli.HELP` (what
`--help` shows).
"""

from robel_dm import command_help
from robel_dm.evaluation import cli


def run() -> None:
  """The command (`robel-evaluate`)."""
  command_help.run_absl(cli.define_flags, cli.main, cli.HELP, cli.__name__)


if __name__ == '__main__':
  run()
