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
  'Success of the training evaluations, held from each evaluation to the '
  'next. Thick: mean over seeds; thin: each seed;\nband: worst to best '
  'seed. A seed that stopped (on success, or at its budget) keeps its '
  'last value to the right edge. Dashed: solved ({solved}).'
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


def _log_steps(axis: Any, steps: Sequence[float]) -> None:
  """A logarithmic env-step axis from the first evaluation after step 0
  to the last."""
  axis.set_xscale('log')
  axis.set_xlim(min(steps), max(steps) * 1.1)


def _to_edge(grid: Any, values: Any, edge: float) -> tuple[Any, Any]:
  """The curves carried on at their last values to `edge` env steps."""
  import numpy as np  # noqa: PLC0415

  if grid[-1] >= edge:
    return grid, values
  return np.append(grid, edge), np.hstack([values, values[:, -1:]])


def task_figure(
  runs: dict[str, Sequence[list[dict]]], title: str, solved: float
) -> Any:
  """Success against env steps (log scale), per agent: each seed thin, the
  mean over seeds thick, shaded from the worst seed to the best.

  Args:
    runs: agent name -> one evaluation log per seed.
    title: the figure's title.
    solved: the success rate that solves the task (a dashed line).

  Returns:
    The matplotlib Figure; the caller saves and closes it.
  """
  pyplot = _pyplot()
  figure, axis = pyplot.subplots(figsize=(6.4, 4.4))
  # Step 0 (the untrained actor) has no place on a log axis.
  curves = {
    name: carried_forward(
      [[row for row in log if row['env_steps'] > 0] for log in logs]
    )
    for name, logs in sorted(runs.items())
  }
  curves = {name: curve for name, curve in curves.items() if len(curve[1])}
  steps = [step for grid, _ in curves.values() for step in grid] or [1, 10]
  for name, (grid, values) in curves.items():
    grid, values = _to_edge(grid, values, max(steps))
    line = axis.step(
      grid,
      values.mean(axis=0),
      where='post',
      linewidth=2.2,
      label=f'{name} ({len(values)} seeds)',
    )[0]
    colour = line.get_color()
    for seed in values:
      axis.step(grid, seed, where='post', color=colour, linewidth=0.9,
                alpha=0.7)  # fmt: skip
    axis.fill_between(
      grid,
      values.min(axis=0),
      values.max(axis=0),
      step='post',
      color=colour,
      alpha=0.12,
      linewidth=0,
    )
  axis.axhline(solved, color='grey', linestyle='--', linewidth=0.9)
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
  caption = _CAPTION.format(solved=solved)
  figure.text(0.5, 0.01, caption, ha='center', va='bottom', fontsize=7)
  figure.tight_layout(rect=(0, 0.08, 1, 1))
  return figure


def plot_task(
  runs: dict[str, Sequence[list[dict]]],
  output: pathlib.Path,
  title: str,
  solved: float,
):
  """Writes `task_figure` as a PNG.

  Args:
    runs: agent name -> one evaluation log per seed.
    output: the PNG to write.
    title: the figure's title.
    solved: the success rate that solves the task.
  """
  figure = task_figure(runs, title, solved)
  figure.savefig(output, dpi=90)
  _pyplot().close(figure)
