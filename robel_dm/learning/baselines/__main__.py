"""`python -m robel_dm.learning.baselines`: see `cli`."""

import sys

from robel_dm.learning.baselines import cli

sys.exit(cli.main())
