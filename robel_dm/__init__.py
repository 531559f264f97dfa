"""robel_dm: ROBEL's D'Claw and D'Kitty benchmarks on dm_control composer."""

import sys
import warnings

__version__ = '0.1.0'

# Before anything imports dm_control, which picks its OpenGL backend once.
from robel_dm import gl_backend  # noqa: E402, F401

# The Gymnasium ids (see robel_dm.learning.gym) must be registered whenever both
# robel_dm and gymnasium are imported, in either order, so that
# `gymnasium.make('robel_dm:robel_dm/DClawTurnFixed-v0')` works even when
# robel_dm was imported first (Gymnasium's `robel_dm:` prefix only imports
# robel_dm, which then does nothing). Registering needs gymnasium and the
# suite (about 0.6 s of imports), so `import robel_dm` does not do it by
# itself:
# * gymnasium already imported: register now.
# * otherwise: a one-shot import hook registers right after gymnasium's first
#   import (its finder only compares module names; it is never used if
#   gymnasium never gets imported, e.g. when it is not installed).


def _register_gymnasium_ids() -> None:
  # When the import of robel_dm.learning.gym is what imported gymnasium,
  # that module is still loading and registers the ids itself at its end.
  if 'robel_dm.learning.gym' not in sys.modules:
    from robel_dm.learning import gym  # noqa: F401, PLC0415


class _GymnasiumImportHook:
  """A meta path finder that registers the ids once gymnasium is imported.

  (Not an `importlib.abc.MetaPathFinder` subclass, and importlib.util is
  imported only when needed: they would cost `import robel_dm` 5-30 ms.)
  """

  def find_spec(self, fullname, path, target=None):
    del path, target
    if fullname != 'gymnasium':
      return None
    if self in sys.meta_path:
      sys.meta_path.remove(self)
    import importlib.util  # noqa: PLC0415

    spec = importlib.util.find_spec(fullname)  # The other finders' spec.
    if spec is None or spec.loader is None:
      return spec
    loader = spec.loader

    def exec_and_register(module):
      del loader.exec_module  # Back to the loader's own method.
      loader.exec_module(module)
      # A broken robel_dm must not break `import gymnasium` for the rest.
      try:
        _register_gymnasium_ids()
      except Exception as error:  # noqa: BLE001
        warnings.warn(
          f'robel_dm could not register its Gymnasium ids: {error!r}',
          stacklevel=2,
        )

    # For this one call only: then the loader is as it was.
    loader.exec_module = exec_and_register
    return spec


if sys.modules.get('gymnasium') is not None:
  _register_gymnasium_ids()
else:
  sys.meta_path.insert(0, _GymnasiumImportHook())
