"""Runs the virtual bus's command line (`cli`)."""

from robel_dm.hardware.virtual import cli

# absl's --help prints the main module's docstring: make it the command's.
__doc__ = cli.__doc__

if __name__ == '__main__':
  cli.main()
