"""Result files say what produced them."""

import numpy as np
import pytest

from robel_dm import provenance


def test_describe_names_software_revision_time_and_machine():
  info = provenance.describe()
  assert {'python', 'robel_dm', 'mujoco', 'dm-control', 'numpy'} <= set(
    info['versions']
  )
  assert info['versions']['mujoco'] == '3.17.0'
  revision = info['git_revision']
  assert revision is None or len(revision.split('+')[0]) == 40
  assert info['timestamp'].endswith('+00:00')
  assert info['machine']['hostname']


def test_spread_gives_a_normal_95_percent_interval():
  values = [0.0, 1.0, 1.0, 0.0, 1.0]
  result = provenance.spread(values)
  std = np.std(values, ddof=1)
  assert result['mean'] == pytest.approx(0.6)
  assert result['std'] == pytest.approx(std)
  half = 1.96 * std / np.sqrt(5)
  assert result['ci95'] == pytest.approx([0.6 - half, 0.6 + half])
  assert provenance.spread([2.0])['ci95'] == [2.0, 2.0]


def test_success_rates_get_a_wilson_interval():
  one_in_four = provenance.proportion([1, 0, 0, 0])
  low, high = one_in_four['ci95']
  assert one_in_four['mean'] == 0.25 and 0.0 < low < 0.25 < high < 1.0
  assert low == pytest.approx(0.0456, abs=1e-3)  # Wilson, z = 1.96.
  assert high == pytest.approx(0.6994, abs=1e-3)
  low, high = provenance.proportion([1, 1, 1, 1])['ci95']
  assert high == 1.0 and low == pytest.approx(0.5101, abs=1e-3)
  assert provenance.proportion([0] * 50)['ci95'][0] == 0.0
