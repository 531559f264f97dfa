"""Learning curves: one run's, and a task's over agents and seeds."""

from collections.abc import Sequence
import json
import pathlib


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


def plot_task(
  runs: dict[str, Sequence[list[dict]]], output: pathlib.Path, title: str
):
  """Success against env steps, one line per agent: the mean over its
  seeds, shaded from the worst seed to the best (like ROBEL's figures).

  Args:
    runs: agent name -> one evaluation log per seed.
    output: the PNG to write.
    title: the figure's title.
  """
  import numpy as np  # noqa: PLC0415

  pyplot = _pyplot()
  figure, axis = pyplot.subplots(figsize=(5.5, 3.6))
  for name, logs in sorted(runs.items()):
    logs = [log for log in logs if log]
    if not logs:
      continue
    grid = sorted({row['env_steps'] for log in logs for row in log})
    values = np.array(
      [
        np.interp(
          grid,
          [row['env_steps'] for row in log],
          [row['success_rate'] for row in log],
          right=np.nan,
        )
        for log in logs
      ]
    )
    mean = np.nanmean(values, axis=0)
    line = axis.plot(grid, mean, label=f'{name} ({len(logs)} seeds)')[0]
    axis.fill_between(
      grid,
      np.nanmin(values, axis=0),
      np.nanmax(values, axis=0),
      color=line.get_color(),
      alpha=0.2,
    )
  axis.set(
    xlabel='env steps',
    ylabel='success rate',
    ylim=(-0.03, 1.03),
    title=title,
  )
  axis.grid(alpha=0.3)
  axis.legend(fontsize=8, loc='lower right')
  figure.tight_layout()
  figure.savefig(output, dpi=90)
  pyplot.close(figure)
