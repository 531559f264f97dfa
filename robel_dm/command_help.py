"""The `--help` of a command line (`robel_dm.commands`): `set_help`, and
`run_absl`, which starts an absl command with it.

A foundation that any command uses; it imports only absl.
"""

from collections.abc import Callable
import sys

from absl import app, flags


def set_help(doc: str, flags_of: str) -> None:
  """Makes the command's `--help` show `doc` and the flags `flags_of` defined.

  absl's `--help` shows the main module's docstring and the flags defined
  there. An installed command's main module is its launcher (the
  `robel-train` script), which has neither, and a command's flags may be
  defined in another module than the one `python -m` runs. Call this after
  defining the flags, before `absl.app.run`.

  Args:
    doc: the command's description.
    flags_of: the name of the module that defined the command's flags.
  """
  sys.modules['__main__'].__doc__ = doc
  for flag in flags.FLAGS.get_key_flags_for_module(flags_of):
    flags.FLAGS.register_key_flag_for_module(sys.argv[0], flag)


def run_absl(
  define_flags: Callable[[], None],
  main: Callable[[list[str]], int | None],
  doc: str,
  flags_of: str,
) -> None:
  """Runs an absl command: defines its flags, makes its `--help` show `doc`
  and those flags (see `set_help`), then runs `main`."""
  define_flags()
  set_help(doc, flags_of)
  app.run(main)
