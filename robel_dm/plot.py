r"""Plots evaluation results side by side: success, score and safety per task.

    python -m robel_dm.plot A.json [B.json ...] --output=fig.png

Each file is the JSON that `python -m robel_dm.evaluate --output=...` writes
(one task) or a list of such results; each file is one series (its label
is the file's name, or `--labels`). Bars show the mean over episodes with a
95% interval (normal approximation, from the per-episode records): success
rate, mean score, and position / velocity safety violations per episode.
Needs matplotlib (the `learn` extra).
"""

from collections.abc import Sequence
import json
import math
import pathlib
import sys
from typing import Any

import numpy as np

from robel_dm import provenance

PANELS = (
  ('success', 'success rate'),
  ('mean_score', 'mean score'),
  ('position', 'position violations / episode'),
  ('velocity', 'velocity violations / episode'),
)


def load_results(path: str | pathlib.Path) -> list[dict[str, Any]]:
  """The evaluation results in a file (one result or a list of them).

  Raises:
    ValueError: if the file is missing or holds no evaluation results.
  """
  path = pathlib.Path(path)
  try:
    data = json.loads(path.read_text())
  except (OSError, json.JSONDecodeError) as error:
    raise ValueError(f'cannot read results from {path}: {error}') from error
  results = data if isinstance(data, list) else [data]
  for result in results:
    if not isinstance(result, dict) or 'records' not in result:
      raise ValueError(f'{path} holds no evaluation results (no "records")')
  return results


def episode_values(result: dict[str, Any], panel: str) -> np.ndarray:
  """One value per episode of a result, for a panel of `PANELS`."""
  records = result['records']
  if panel in ('position', 'velocity', 'current'):
    return np.array([r['safety'][panel] for r in records], float)
  return np.array([float(r[panel]) for r in records], float)


def mean_and_interval(values: np.ndarray) -> tuple[float, float]:
  """The mean and the half-width of its 95% interval."""
  result = provenance.spread(values)
  return result['mean'], result['ci95'][1] - result['mean']


def plot(
  paths: Sequence[str],
  output: str | pathlib.Path,
  labels: Sequence[str] | None = None,
) -> pathlib.Path:
  """Draws one panel per metric, tasks on the x axis, a bar per file.

  Returns:
    The written image's path.

  Raises:
    ValueError: for unreadable files or a wrong number of labels.
  """
  import matplotlib  # noqa: PLC0415 (only the plot command needs it)

  matplotlib.use('Agg')
  from matplotlib import pyplot  # noqa: PLC0415

  series = [load_results(path) for path in paths]
  labels = list(labels) if labels else [pathlib.Path(p).stem for p in paths]
  if len(labels) != len(series):
    raise ValueError(f'{len(labels)} labels for {len(series)} result files')
  tasks = sorted(
    {f'{r["domain"]}/{r["task"]}' for results in series for r in results}
  )
  figure, axes = pyplot.subplots(
    1, len(PANELS), figsize=(4 * len(PANELS), 3.5), squeeze=False
  )
  width = 0.8 / len(series)
  x = np.arange(len(tasks))
  for panel_axes, (panel, title) in zip(axes[0], PANELS, strict=True):
    for i, (label, results) in enumerate(zip(labels, series, strict=True)):
      by_task = {f'{r["domain"]}/{r["task"]}': r for r in results}
      stats = [
        mean_and_interval(episode_values(by_task[task], panel))
        if task in by_task
        else (math.nan, math.nan)
        for task in tasks
      ]
      means, intervals = zip(*stats, strict=True)
      panel_axes.bar(
        x + (i - (len(series) - 1) / 2) * width,
        means,
        width,
        yerr=intervals,
        capsize=3,
        label=label,
      )
    panel_axes.set_title(title)
    panel_axes.set_xticks(x, tasks, rotation=45, ha='right')
  axes[0][0].legend()
  figure.tight_layout()
  output = pathlib.Path(output)
  figure.savefig(output, dpi=100)
  pyplot.close(figure)
  return output


def main(argv: Sequence[str] | None = None) -> int:
  import argparse  # noqa: PLC0415

  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('results', nargs='+', help='evaluation JSON files')
  parser.add_argument('--output', required=True, help='image to write')
  parser.add_argument('--labels', default=None, help='comma-separated')
  args = parser.parse_args(argv)
  try:
    written = plot(
      args.results,
      args.output,
      args.labels.split(',') if args.labels else None,
    )
  except (ValueError, OSError) as error:
    print(f'error: {error}', file=sys.stderr)
    return 2
  print(f'wrote {written}')
  return 0


if __name__ == '__main__':
  sys.exit(main())
