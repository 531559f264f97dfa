"""Locates the MJCF models, in a source checkout or an installed wheel."""

import functools
import importlib.resources
import pathlib

# Wheels carry the repository's `xml/` folder inside the package as `xml/`,
# and its `policies/` folder (the shipped baselines) as `baseline_policies/`.
_PACKAGED_DIR = 'xml'
_PACKAGED_BASELINES = 'baseline_policies'


@functools.cache
def xml_dir() -> pathlib.Path:
  """Returns the folder that holds the robot and prop models.

  Raises:
    FileNotFoundError: if neither an installed copy nor a checkout copy exists.
  """
  packaged = pathlib.Path(
    str(importlib.resources.files('robel_dm') / _PACKAGED_DIR)
  )
  checkout = pathlib.Path(__file__).resolve().parent.parent / 'xml'
  for candidate in (packaged, checkout):
    if candidate.is_dir():
      return candidate
  raise FileNotFoundError(
    f'robel_dm models not found: looked in {packaged} (installed wheel) and '
    f'{checkout} (source checkout). Reinstall robel_dm.'
  )


def xml_path(*parts: str) -> pathlib.Path:
  """Returns the path of a model file, e.g. `xml_path('dclaw', 'dclaw.xml')`.

  Raises:
    FileNotFoundError: if the file does not exist.
  """
  path = xml_dir().joinpath(*parts)
  if not path.is_file():
    raise FileNotFoundError(f'robel_dm model file missing: {path}')
  return path


@functools.cache
def baselines_dir() -> pathlib.Path:
  """The folder of the shipped baseline policies (may be empty)."""
  packaged = pathlib.Path(
    str(importlib.resources.files('robel_dm') / _PACKAGED_BASELINES)
  )
  checkout = pathlib.Path(__file__).resolve().parent.parent / 'policies'
  return packaged if packaged.is_dir() else checkout
