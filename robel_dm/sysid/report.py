"""The result of a system identification as text: `fit_table` (the
values and errors per joint, what `robel-sysid fit` prints) and
`warning_lines` (one per poorly determined value)."""

import numpy as np

from robel_dm.sysid import fit

# Characters of a parameter's column: a value, its flag and a ratio such as
# ' 1.2x' (ratios up to 99.9x).
_CELL = 15


def _cell(result: fit.FitResult, joint: int, parameter: str) -> str:
  """A fitted value, '?' if not identified, and its ratio to the model's."""
  value = result.fitted[parameter][joint]
  name = f'{result.joint_names[joint]}.{parameter}'
  flag = '?' if name in result.not_identified else ' '
  nominal = result.nominal[parameter][joint]
  if nominal <= 0:  # No ratio to a model value of zero (friction loss).
    return f'{value:>{_CELL - 1}.4g}{flag}'
  return f'{value:>{_CELL - 6}.4g}{flag}{value / nominal:>4.1f}x'


def fit_table(result: fit.FitResult) -> str:
  """The fit as a table: per joint, the values and the angle error."""
  names = list(result.fitted)
  header = f'{"joint":<8}' + ''.join(f'{n:>{_CELL}}' for n in names)
  header += f'{"RMS error (deg): model":>26}{"fit":>8}'
  lines = [header]
  for j, joint in enumerate(result.joint_names):
    cells = ''.join(_cell(result, j, n) for n in names)
    before, after = np.degrees([result.rms_before[j], result.rms_after[j]])
    lines.append(f'{joint:<8}{cells}{before:>26.3f}{after:>8.3f}')
  lines.append(
    f'control delay {result.control_delay * 1e3:.1f} ms; RMS angle error '
    f'{np.degrees(np.sqrt(np.mean(result.rms_before**2))):.3f} -> '
    f'{np.degrees(np.sqrt(np.mean(result.rms_after**2))):.3f} deg; '
    f'{result.evaluations} simulations'
  )
  lines += warning_lines(result)
  return '\n'.join(lines)


def warning_lines(result: fit.FitResult) -> list[str]:
  """One line per poorly determined value (marked '?' in the table)."""
  lines = []
  for name, reason in result.poorly_determined.items():
    joint, parameter = name.split('.')
    j = result.joint_names.index(joint)
    value = result.fitted[parameter][j]
    error = result.standard_error[parameter][j]
    lines.append(
      f'? warning: {name} = {value:.4g} +- {error:.2g} (standard error) is '
      f'poorly determined: {reason}'
    )
  return lines
