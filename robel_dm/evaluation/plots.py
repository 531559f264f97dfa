r"""Plots evaluation results side by side: success, score and safety per task.

Each file is the JSON that `robel-evaluate --output=...` writes (one task) or
a list of such results (a sweep); each file is one series. One row of panels
per robot (their scores and violation counts differ in scale), one
horizontal bar per task and series: the mean over episodes with a 95%
interval computed from the per-episode records, Wilson's for the success
rate and a percentile bootstrap of the mean for the score and the violation
counts (so an interval stays within the values an episode can take: never
below zero). `plot` draws files into an image (the `robel-plot` command);
needs matplotlib (the `learn` extra).
"""

from collections.abc import Sequence
import json
import math
import pathlib
from typing import Any

import numpy as np

from robel_dm import constants, provenance

PANELS = (
  ('success', 'success rate'),
  ('mean_score', 'mean score'),
  ('position', 'position violations / episode'),
  ('velocity', 'velocity violations / episode'),
)
# Bootstrap resamples of an interval, and their seed (the figure of the same
# files is the same figure).
BOOTSTRAP_RESAMPLES = 2000
_BOOTSTRAP_SEED = 0
INTERVALS_NOTE = (
  'bars: mean over episodes; 95% intervals: Wilson (success rate), '
  'percentile bootstrap of the mean (score, violations)'
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


def interval(panel: str, values: np.ndarray) -> tuple[float, float, float]:
  """The mean of a panel's per-episode values and its 95% interval (low,
  high): Wilson's for the success rate, otherwise a percentile bootstrap of
  the mean, which stays within the values' range (counts never go below
  zero)."""
  values = np.asarray(values, float)
  if not values.size:
    return math.nan, math.nan, math.nan
  if panel == 'success':
    result = provenance.proportion(values)
    return result['mean'], *result['ci95']
  rng = np.random.default_rng(_BOOTSTRAP_SEED)
  picks = rng.integers(0, values.size, (BOOTSTRAP_RESAMPLES, values.size))
  means = values[picks].mean(axis=1)
  low, high = np.percentile(means, [2.5, 97.5])
  return float(values.mean()), float(low), float(high)


def draw(series: Sequence[list[dict[str, Any]]], labels: Sequence[str]):
  """The figure: a row of `PANELS` per robot domain, a bar per task (y axis)
  and series.

  Returns:
    The matplotlib Figure.
  """
  from matplotlib import pyplot  # noqa: PLC0415

  domains = sorted({r['domain'] for results in series for r in results})
  tasks = {
    domain: sorted(
      {
        r['task']
        for results in series
        for r in results
        if r['domain'] == domain
      }  # fmt: skip
    )
    for domain in domains
  }
  rows = [len(tasks[d]) * len(series) * 0.22 + 0.9 for d in domains]
  figure, axes = pyplot.subplots(
    len(domains), len(PANELS), squeeze=False,
    figsize=(3.6 * len(PANELS), sum(rows) + 1.0),
    gridspec_kw={'height_ratios': rows},
  )  # fmt: skip
  height = 0.8 / len(series)
  colors = pyplot.rcParams['axes.prop_cycle'].by_key()['color']
  for row, domain in enumerate(domains):
    y = np.arange(len(tasks[domain]))
    for column, (panel, title) in enumerate(PANELS):
      panel_axes = axes[row][column]
      for i, results in enumerate(series):
        by_task = {r['task']: r for r in results if r['domain'] == domain}
        stats = np.array(
          [
            interval(panel, episode_values(by_task[task], panel))
            if task in by_task
            else (math.nan,) * 3
            for task in tasks[domain]
          ]
        )
        means, lows, highs = stats.T
        panel_axes.barh(
          y + (i - (len(series) - 1) / 2) * height, means, height,
          xerr=[means - lows, highs - means], capsize=2,
          color=colors[i % len(colors)], label=labels[i],
        )  # fmt: skip
      panel_axes.set_yticks(y, tasks[domain] if column == 0 else [])
      panel_axes.invert_yaxis()  # The first task on top.
      panel_axes.set_xlim(left=0)
      if panel == 'success':
        panel_axes.set_xlim(0, 1.05)
      panel_axes.set_title(f'{domain}: {title}', fontsize=9)
      panel_axes.tick_params(labelsize=8)
      panel_axes.grid(axis='x', alpha=0.3)
  handles, names = axes[0][0].get_legend_handles_labels()
  inches = figure.get_size_inches()[1]
  figure.legend(handles, names, loc='lower center', ncol=min(len(series), 4),
                frameon=False, fontsize=9)  # fmt: skip
  legend_rows = math.ceil(len(series) / 4)
  note_at = (0.3 * legend_rows + 0.05) / inches
  figure.text(0.5, note_at, INTERVALS_NOTE, fontsize=7, color='0.3',
              ha='center')  # fmt: skip
  figure.tight_layout(rect=(0, note_at + 0.2 / inches, 1, 1))
  return figure


def plot(
  paths: Sequence[str],
  output: str | pathlib.Path,
  labels: Sequence[str] | None = None,
) -> pathlib.Path:
  """Draws the results of each file (see `draw`) into `output`.

  Returns:
    The written image's path.

  Raises:
    ValueError: for unreadable files or a wrong number of labels.
    ModuleNotFoundError: without matplotlib (the learn extra).
  """
  try:
    import matplotlib  # noqa: PLC0415 (only the plot command needs it)
  except ImportError as error:
    raise ModuleNotFoundError(
      'plots need matplotlib: ' + constants.INSTALL_EXTRA.format('learn'),
      name=error.name,
    ) from error

  matplotlib.use('Agg')
  from matplotlib import pyplot  # noqa: PLC0415

  series = [load_results(path) for path in paths]
  labels = list(labels) if labels else [pathlib.Path(p).stem for p in paths]
  if len(labels) != len(series):
    raise ValueError(f'{len(labels)} labels for {len(series)} result files')
  figure = draw(series, labels)
  output = pathlib.Path(output)
  figure.savefig(output, dpi=100)
  pyplot.close(figure)
  return output
