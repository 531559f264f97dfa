"""What a result file records so that runs can be compared and reproduced.

`describe()` gives the software (robel_dm, MuJoCo, dm_control, numpy,
Python and, when present, dynamixel-sdk, Gymnasium, Stable-Baselines3,
torch), the git revision of a source checkout (with `+dirty` for local
changes), the UTC time and the machine. `spread()` gives the mean, the
standard deviation and a 95% interval of per-episode values;
`proportion()` the same for successes, with a Wilson score interval.
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


def proportion(successes) -> dict[str, Any]:
  """Rate, standard deviation and a 95% Wilson score interval of
  per-episode successes: inside [0, 1] and not empty when every episode
  succeeds or fails (a normal interval gives -0.24..0.74 for 1 in 4, and
  1.00..1.00 for 4 in 4)."""
  values = np.asarray(successes, dtype=float)
  n = values.size
  if not n:
    return {
      'mean': math.nan,
      'std': math.nan,
      'ci95': [math.nan, math.nan],
      'interval': 'wilson',
    }
  rate = float(values.mean())
  z2 = _Z95**2
  centre = (rate + z2 / (2 * n)) / (1 + z2 / n)
  half = (
    _Z95 * math.sqrt(rate * (1 - rate) / n + z2 / (4 * n * n)) / (1 + z2 / n)
  )
  return {
    'mean': rate,
    'std': float(values.std(ddof=1)) if n > 1 else 0.0,
    'ci95': [max(0.0, centre - half), min(1.0, centre + half)],
    'interval': 'wilson',
  }
