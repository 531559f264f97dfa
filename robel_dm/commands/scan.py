"""Runs the scan's command line (`cli`)."""

from robel_dm.hardware.scan import cli

if __name__ == '__main__':
  cli.main()
