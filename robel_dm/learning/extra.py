"""The one line a missing package of the learn extra gives."""


def missing(error: ImportError) -> ModuleNotFoundError:
  """The error to raise, from `error`, when an import of the learn extra
  fails: it names the missing package and the extra to install."""
  return ModuleNotFoundError(
    f'robel_dm.learning needs the learn extra ({error.name} is missing): '
    'pip install -e ".[learn]" (in the checkout)',
    name=error.name,
  )
