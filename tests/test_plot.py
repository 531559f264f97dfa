"""The plot command draws evaluation results of several runs."""

import json
import subprocess
import sys

import numpy as np
import pytest

from robel_dm import evaluate, plot

pytest.importorskip('matplotlib')


@pytest.fixture(scope='module')
def result_files(tmp_path_factory):
  directory = tmp_path_factory.mktemp('results')
  paths = []
  for policy in ('zero', 'reference'):
    result = evaluate.evaluate('dclaw', 'pose_fixed', 3, policy=policy)
    path = directory / f'{policy}.json'
    path.write_text(json.dumps(result))
    paths.append(path)
  return paths


def test_intervals_come_from_the_episode_records():
  mean, half = plot.mean_and_interval(np.array([0.0, 1.0, 1.0, 0.0]))
  assert mean == 0.5
  assert half == pytest.approx(1.96 * np.std([0, 1, 1, 0], ddof=1) / 2)


def test_plot_command_writes_the_figure(result_files, tmp_path):
  output = tmp_path / 'fig.png'
  result = subprocess.run(
    [sys.executable, '-m', 'robel_dm.plot', *map(str, result_files),
     f'--output={output}', '--labels=zero,reference'],
    capture_output=True, text=True, check=False,
  )  # fmt: skip
  assert result.returncode == 0, result.stderr
  assert output.stat().st_size > 10_000
  assert output.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'


def test_plot_rejects_files_without_results(tmp_path):
  bad = tmp_path / 'bad.json'
  bad.write_text('{"not": "results"}')
  assert plot.main([str(bad), f'--output={tmp_path / "x.png"}']) == 2
