"""Points to the virtual bus's command line, `robel_dm.tools.virtual_bus`.

Importing it from here would make the hardware layer import the suite above
it; this stub only points the way.
"""

import sys

if __name__ == '__main__':
  sys.exit(
    'the virtual bus is served by `python -m robel_dm.tools.virtual_bus` '
    '(same flags)'
  )
