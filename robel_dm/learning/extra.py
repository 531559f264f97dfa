"""The one line a missing package of the learn extra gives."""

from robel_dm import constants


def missing(error: ImportError) -> ModuleNotFoundError:
  """The error to raise, from `error`, when an import of the learn extra
  fails: it names the missing package and the extra to install."""
  return ModuleNotFoundError(
    f'robel_dm.learning needs the learn extra ({error.name} is missing): '
    + constants.INSTALL_EXTRA.format('learn'),
    name=error.name,
  )
