"""Per-task learning-curve figures: seeds carried forward, log steps."""

import numpy as np
import pytest

from robel_dm.learning import curves

pytest.importorskip('matplotlib', reason='needs robel_dm[learn]')


def _log(*points):
  return [{'env_steps': s, 'success_rate': v} for s, v in points]


# Seed 0 stopped on success at 20k; seed 1 ran on to 60k without success.
_EARLY = _log((0, 0.0), (10_000, 0.5), (20_000, 0.9))
_LONG = _log((0, 0.0), (20_000, 0.0), (40_000, 0.1), (60_000, 0.2))


def test_a_curve_that_stopped_on_success_keeps_its_last_value():
  grid, values = curves.carried_forward([_EARLY, _LONG])
  assert list(grid) == [0, 10_000, 20_000, 40_000, 60_000]
  assert values.shape == (2, 5)
  assert not np.isnan(values).any()
  np.testing.assert_allclose(values[0], [0.0, 0.5, 0.9, 0.9, 0.9])
  np.testing.assert_allclose(values[1], [0.0, 0.0, 0.0, 0.1, 0.2])
  np.testing.assert_allclose(values.mean(axis=0)[-1], 0.55)


def test_a_curve_skips_empty_logs_and_sorts_rows():
  grid, values = curves.carried_forward([[], list(reversed(_EARLY))])
  assert list(grid) == [0, 10_000, 20_000]
  np.testing.assert_allclose(values, [[0.0, 0.5, 0.9]])
  grid, values = curves.carried_forward([[]])
  assert values.shape == (0, 0)


@pytest.mark.slow
def test_a_task_figure_has_log_steps_seed_lines_and_a_caption():
  from matplotlib import pyplot  # noqa: PLC0415

  figure = curves.task_figure(
    {'sac': [_EARLY, _LONG], 'trpo': [_log((0, 0.0), (2_000_000, 0.4))]},
    'dclaw/turn_fixed',
    0.8,
  )
  try:
    (axis,) = figure.axes
    assert axis.get_xscale() == 'log'
    # From the first evaluation after step 0; every agent to the edge.
    assert axis.get_xlim()[0] == 10_000
    assert axis.get_xlim()[1] >= 2_000_000
    assert all(line.get_xdata()[-1] == 2_000_000 for line in axis.get_lines()
               if len(line.get_xdata()) > 2)  # fmt: skip
    assert 'log scale' in axis.get_xlabel()
    labels = axis.get_legend_handles_labels()[1]
    assert labels == ['sac (2 seeds)', 'trpo (1 seeds)']
    # Per agent one thick mean line and one thin line per seed; the bar.
    assert len(axis.get_lines()) == (1 + 2) + (1 + 1) + 1
    widths = sorted({line.get_linewidth() for line in axis.get_lines()})
    assert widths[0] < widths[-1]
    caption = ' '.join(text.get_text() for text in figure.texts)
    assert 'worst to best seed' in caption and 'solved (0.8)' in caption
  finally:
    pyplot.close(figure)


@pytest.mark.slow
def test_plot_task_writes_a_png(tmp_path):
  output = tmp_path / 'task.png'
  curves.plot_task(
    {'sac': [_EARLY, _LONG, []]}, output, 'dclaw/turn_fixed', 0.8
  )
  assert output.read_bytes().startswith(b'\x89PNG')
