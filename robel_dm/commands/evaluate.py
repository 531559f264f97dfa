"""The evaluation command: `python -m robel_dm.evaluate` (or `robel-evaluate`).

Evaluates a policy on robel_dm tasks and reports ROBEL's metrics; see
`robel_dm.evaluation.cli.HELP` for its use (what `--help` shows).
"""

from robel_dm.evaluation import cli

if __name__ == '__main__':
  cli.run()
