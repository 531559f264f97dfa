r"""Evaluates a policy on a robel_dm task and reports ROBEL's metrics.

    python -m robel_dm.evaluate --domain=dclaw --task=pose_fixed \
        --policy=reference --episodes=20 --output=results.json

Prints one row per episode and a summary, and optionally writes JSON with the
success rate (ROBEL's success evaluator: the `success` signal at each
episode's last step), mean return, mean score, mean safety violations per
episode and the control steps per second.
"""

from absl import app, flags

from robel_dm.evaluation import cli

if __name__ == '__main__':
  cli.define_flags()
  flags.adopt_module_key_flags(cli)  # --help lists them as this command's.
  app.run(cli.main)
