"""Learning curves: one run's, and a task's over agents and seeds."""

from collections.abc import Sequence
import json
import pathlib
from typing import Any


def _pyplot():
  import matplotlib  # noqa: PLC0415 (only plotting needs it)

  matplotlib.use('Agg')
  from matplotlib import pyplot  # noqa: PLC0415

  return pyplot


def read_log(path: pathlib.Path) -> list[dict]:
  return [
    json.loads(line) for line in pathlib.Path(path).read_text().splitlines()
  ]


def plot_run(log_path: pathlib.Path, output: pathlib.Path, title: str):
  """Success rate, mean score, mean return and safety violations per
  episode against env steps (epochs for behaviour cloning)."""
  rows = read_log(log_path)
  if not rows:
    return
  pyplot = _pyplot()
  by_epoch = 'epoch' in rows[0]
  x = [row['epoch' if by_epoch else 'env_steps'] for row in rows]
  figure, axes = pyplot.subplots(1, 4, figsize=(15, 3.2))
  axes[0].plot(x, [row['success_rate'] for row in rows], marker='.')
  axes[0].set(ylabel='success rate', ylim=(-0.05, 1.05))
  scores = [row['mean_score'] for row in rows]
  axes[1].plot(x, scores, marker='.')
  axes[1].set(ylabel='mean score', ylim=(min(0, *scores), max(1, *scores)))
  axes[2].plot(x, [row['mean_return'] for row in rows], marker='.')
  axes[2].set(ylabel='mean return')
  for name in rows[0]['safety']:
    axes[3].plot(x, [row['safety'][name] for row in rows], label=name)
  axes[3].set(ylabel='violations / episode', ylim=(0, None))
  axes[3].legend(fontsize=7)
  for axis in axes:
    axis.set_xlabel('epochs' if by_epoch else 'env steps')
    axis.grid(alpha=0.3)
  figure.suptitle(title)
  figure.tight_layout()
  figure.savefig(output, dpi=90)
  pyplot.close(figure)


_CAPTION = (
  'thick: mean over seeds; thin: each seed; band: worst to best seed; '
  'a seed that stopped on success keeps its last value'
)


def carried_forward(logs: Sequence[list[dict]]) -> tuple[Any, Any]:
  """Puts one agent's seeds on a shared grid of env steps.

  Every evaluation step of any seed is a grid point. Between its own
  evaluations a seed is interpolated; after its last one it keeps its last
  success rate (runs stop at their first evaluation at 80% success, so a
  run that stopped early stopped on success).

  Args:
    logs: one evaluation log per seed, rows with 'env_steps' and
      'success_rate'; empty logs are skipped.

  Returns:
    The grid (steps, ascending) and a seeds x grid array of success rates,
    without NaN.
  """
  import numpy as np  # noqa: PLC0415

  logs = [sorted(log, key=lambda row: row['env_steps']) for log in logs if log]
  grid = np.unique([row['env_steps'] for log in logs for row in log])
  values = np.array(
    [
      np.interp(
        grid,
        [row['env_steps'] for row in log],
        [row['success_rate'] for row in log],
      )
      for log in logs
    ]
  ).reshape(len(logs), len(grid))
  return grid, values


def _log_steps(axis: Any, steps: Sequence[float]):
  """Log-scales the step axis, keeping step 0: linear from 0 to the power
  of ten at or below the first positive step, logarithmic beyond it."""
  import numpy as np  # noqa: PLC0415

  positive = [step for step in steps if step > 0] or [1e3]
  low = int(np.floor(np.log10(min(positive))))
  high = int(np.floor(np.log10(max(positive))))
  axis.set_xscale('symlog', linthresh=10.0**low, linscale=0.3)
  axis.set_xticks([0] + [10.0**power for power in range(low, high + 1)])
  axis.set_xlim(0, max(positive) * 1.15)


def task_figure(runs: dict[str, Sequence[list[dict]]], title: str) -> Any:
  """Success against env steps (log scale), per agent: each seed thin, the
  mean over seeds thick, shaded from the worst seed to the best.

  Args:
    runs: agent name -> one evaluation log per seed.
    title: the figure's title.

  Returns:
    The matplotlib Figure; the caller saves and closes it.
  """
  pyplot = _pyplot()
  figure, axis = pyplot.subplots(figsize=(6, 4))
  steps = []
  for name, logs in sorted(runs.items()):
    grid, values = carried_forward(logs)
    if not len(values):
      continue
    steps.extend(grid)
    line = axis.plot(
      grid,
      values.mean(axis=0),
      linewidth=2.2,
      label=f'{name} ({len(values)} seeds)',
    )[0]
    colour = line.get_color()
    for seed in values:
      axis.plot(grid, seed, color=colour, linewidth=0.8, alpha=0.6)
    axis.fill_between(
      grid,
      values.min(axis=0),
      values.max(axis=0),
      color=colour,
      alpha=0.15,
      linewidth=0,
    )
  _log_steps(axis, steps)
  axis.set(
    xlabel='env steps (log scale)',
    ylabel='success rate',
    ylim=(-0.03, 1.03),
    title=title,
  )
  axis.grid(alpha=0.3, which='both')
  if axis.get_legend_handles_labels()[0]:
    axis.legend(fontsize=8, loc='upper left')
  figure.text(0.5, 0.01, _CAPTION, ha='center', va='bottom', fontsize=6.5)
  figure.tight_layout(rect=(0, 0.04, 1, 1))
  return figure


def plot_task(
  runs: dict[str, Sequence[list[dict]]], output: pathlib.Path, title: str
):
  """Writes `task_figure` as a PNG.

  Args:
    runs: agent name -> one evaluation log per seed.
    output: the PNG to write.
    title: the figure's title.
  """
  figure = task_figure(runs, title)
  figure.savefig(output, dpi=90)
  _pyplot().close(figure)
