"""The plain-text table of an evaluation: a row per episode, a summary."""

from typing import Any

_ROW_HEADER = (
  f'{"episode":>7} {"seed":>6} {"return":>10} {"mean score":>10} '
  f'{"success":>7} {"pos/vel/cur violations":>22}'
)


def format_row(index: int, record: dict[str, Any]) -> str:
  """One episode's line of the table."""
  safety = '/'.join(str(v) for v in record['safety'].values())
  return (
    f'{index:>7} {record["seed"]!s:>6} {record["return"]:>10.2f} '
    f'{record["mean_score"]:>10.3f} '
    f'{"yes" if record["success"] else "no":>7} {safety:>22}'
  )


def format_header(results: dict[str, Any]) -> str:
  return (
    f'{results["domain"]}/{results["task"]}  policy={results["policy"]}  '
    f'seed={results["seed"]}  task_kwargs={results["task_kwargs"]}\n'
    f'{_ROW_HEADER}\n{"-" * len(_ROW_HEADER)}'
  )


def format_summary(results: dict[str, Any]) -> str:
  """The summary lines under the episode rows."""
  spread = results['spread']
  safety = results['safety']
  return '\n'.join(
    [
      '-' * len(_ROW_HEADER),
      f'success rate      {results["success_rate"]:.2f} '
      f'({results["episodes"]} episodes; 95% Wilson interval '
      f'{spread["success"]["ci95"][0]:.2f}..{spread["success"]["ci95"][1]:.2f})',
      f'mean return       {results["mean_return"]:.2f} '
      f'(std {spread["return"]["std"]:.2f})',
      f'mean score        {results["mean_score"]:.3f} '
      f'(std {spread["mean_score"]["std"]:.3f})',
      'safety / episode  '
      + ', '.join(f'{field} {value:.2f}' for field, value in safety.items()),
      f'steps per second  {results["steps_per_second"]:.0f}',
    ]
  )
