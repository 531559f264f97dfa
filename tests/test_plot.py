"""The plot command draws evaluation results of several runs."""

import json
import subprocess
import sys

import numpy as np
import pytest

from robel_dm import evaluation
from robel_dm.commands import plot as plot_command
from robel_dm.evaluation import plots

pytest.importorskip('matplotlib', reason='needs robel_dm[learn]')


@pytest.fixture(scope='module')
def result_files(tmp_path_factory):
  directory = tmp_path_factory.mktemp('results')
  paths = []
  for policy in ('zero', 'reference'):
    result = evaluation.evaluate(
      evaluation.EvalConfig('dclaw', 'pose_fixed', 3, policy=policy)
    )
    path = directory / f'{policy}.json'
    path.write_text(json.dumps(result))
    paths.append(path)
  return paths


def test_a_success_rate_gets_wilsons_interval():
  rate, low, high = plots.interval('success', np.array([1.0, 0, 0, 0]))
  assert rate == 0.25
  assert (low, high) == pytest.approx((0.0456, 0.6994), abs=1e-3)
  rate, low, high = plots.interval('success', np.ones(4))
  assert rate == high == 1.0 and low < 0.6  # Not 1.00..1.00.


def test_a_count_interval_never_goes_below_zero():
  counts = np.array([0.0, 0, 0, 5])
  # The normal interval the plot used to draw: below zero.
  assert counts.mean() - 1.96 * counts.std(ddof=1) / 2 < 0
  mean, low, high = plots.interval('position', counts)
  assert mean == 1.25 and 0 <= low <= mean <= high <= 5
  # The same files give the same figure.
  assert plots.interval('position', counts) == (mean, low, high)


@pytest.mark.slow
def test_a_sweep_gets_a_row_of_panels_per_robot():
  def result(domain, task):
    return {'domain': domain, 'task': task, 'records': [
      {'success': True, 'mean_score': 0.5,
       'safety': {'position': 1, 'velocity': 0, 'current': 0}}]}  # fmt: skip

  sweep = [result('dclaw', t) for t in ('pose_fixed', 'turn_fixed')]
  sweep += [result('dkitty', t) for t in ('stand_fixed', 'walk_fixed')]
  figure = plots.draw([sweep, sweep[:1]], ['a', 'b'])
  axes = figure.axes
  assert len(axes) == 2 * len(plots.PANELS)
  rows = [[t.get_text() for t in a.get_yticklabels()] for a in axes[::4]]
  assert rows == [['pose_fixed', 'turn_fixed'], ['stand_fixed', 'walk_fixed']]
  assert axes[0].get_title().startswith('dclaw')
  assert axes[4].get_title().startswith('dkitty')
  # The legend is the figure's, outside the panels.
  assert not any(a.get_legend() for a in axes) and figure.legends


@pytest.mark.slow
def test_plot_command_writes_the_figure(result_files, tmp_path):
  output = tmp_path / 'fig.png'
  result = subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.plot', *map(str, result_files),
     f'--output={output}', '--labels=zero,reference'],
    capture_output=True, text=True, check=False,
  )  # fmt: skip
  assert result.returncode == 0, result.stderr
  assert output.stat().st_size > 10_000
  assert output.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_plot_rejects_files_without_results(tmp_path):
  bad = tmp_path / 'bad.json'
  bad.write_text('{"not": "results"}')
  assert plot_command.main([str(bad), f'--output={tmp_path / "x.png"}']) == 2
