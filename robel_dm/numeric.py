"""What counts as a number in task options, robot configurations and
calibrations.

Python counts `True` as the integer 1; an option given `true` by mistake
must not pass for 1.
"""

import math
import numbers
from typing import Any


def is_real(value: Any) -> bool:
  """A real number (ints and floats, numpy's too), not a bool."""
  return isinstance(value, numbers.Real) and not isinstance(value, bool)


def is_finite(value: Any) -> bool:
  """A real number (`is_real`) that is neither infinite nor NaN."""
  return is_real(value) and math.isfinite(value)


def is_integer(value: Any) -> bool:
  """An integer (numpy's too), not a bool."""
  return isinstance(value, numbers.Integral) and not isinstance(value, bool)
