"""What a result file records so that runs can be compared and reproduced.

`describe()` gives the software (robel_dm, MuJoCo, dm_control, numpy,
Python and, when present, dynamixel-sdk, Gymnasium, Stable-Baselines3,
torch), the git revision of a source checkout (with `+dirty` for local
changes), the UTC time and the machine. `spread()` gives the mean, the
standard deviation and a 95% interval of per-episode values.
"""

import datetime
import importlib.metadata
import math
import pathlib
import platform
import socket
import subprocess
from typing import Any

import numpy as np

# z of a two-sided 95% normal interval.
_Z95 = 1.96
_PACKAGES = (
  'robel_dm',
  'mujoco',
  'dm-control',
  'numpy',
  'dynamixel-sdk',
  'gymnasium',
  'stable-baselines3',
  'torch',
)
_CHECKOUT = pathlib.Path(__file__).resolve().parent.parent


def versions() -> dict[str, str]:
  """Installed versions of the packages a result depends on."""
  found = {'python': platform.python_version()}
  for name in _PACKAGES:
    try:
      found[name] = importlib.metadata.version(name)
    except importlib.metadata.PackageNotFoundError:
      continue
  return found


def _git(*args: str) -> str:
  return subprocess.run(
    ['git', *args],
    cwd=_CHECKOUT,
    capture_output=True,
    text=True,
    check=True,
    timeout=10,
  ).stdout.strip()


def git_revision() -> str | None:
  """The source checkout's commit (+dirty), or None outside a checkout."""
  if not (_CHECKOUT / '.git').exists():
    return None
  try:
    revision = _git('rev-parse', 'HEAD')
    dirty = _git('status', '--porcelain', '--untracked-files=no')
  except (OSError, subprocess.SubprocessError):
    return None
  return revision + ('+dirty' if dirty else '')


def describe() -> dict[str, Any]:
  """Software, revision, time and machine of this run."""
  return {
    'versions': versions(),
    'git_revision': git_revision(),
    'timestamp': datetime.datetime.now(datetime.timezone.utc).isoformat(),
    'machine': {
      'hostname': socket.gethostname(),
      'platform': platform.platform(),
      'processor': platform.machine(),
    },
  }


def spread(values) -> dict[str, float]:
  """Mean, sample standard deviation and a 95% interval of the mean."""
  values = np.asarray(values, dtype=float)
  if not values.size:
    return {'mean': math.nan, 'std': math.nan, 'ci95': [math.nan, math.nan]}
  mean = float(values.mean())
  std = float(values.std(ddof=1)) if values.size > 1 else 0.0
  half = _Z95 * std / math.sqrt(values.size)
  return {'mean': mean, 'std': std, 'ci95': [mean - half, mean + half]}
