"""robel_dm: ROBEL's D'Claw and D'Kitty benchmarks on dm_control composer."""

import sys

__version__ = '0.1.0'

if 'gymnasium' in sys.modules:
  # gymnasium.make('robel_dm:robel_dm/DClawTurnFixed-v0') imports this
  # package first: register the Gymnasium ids (see robel_dm.gym).
  from robel_dm import gym as _gym  # noqa: F401
