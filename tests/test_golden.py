"""Every task reproduces its golden trajectories bit for bit (see golden.py).

A failure names the quantities that changed and by how much (their episode
sums). If the change is deliberate, regenerate the file with
`python tests/golden.py` and say why in the commit.
"""

import json

import golden
import pytest

_GOLDEN = json.loads(golden.PATH.read_text())
_CONFIGS = golden.configurations()


def test_every_configuration_is_pinned():
  assert sorted(_GOLDEN) == sorted(golden.name(*c) for c in _CONFIGS)


@pytest.mark.parametrize(
  'config', _CONFIGS, ids=[golden.name(*c) for c in _CONFIGS]
)
def test_trajectories_match_bit_for_bit(config):
  expected = _GOLDEN[golden.name(*config)]
  actual = golden.record(*config)
  for episode, (want, got) in enumerate(zip(expected, actual, strict=True)):
    assert got['steps'] == want['steps'], f'episode {episode} length'
    assert sorted(got['digests']) == sorted(want['digests'])
    changed = {
      key: (want['digests'][key]['sum'], value['sum'])
      for key, value in got['digests'].items()
      if value['sha256'] != want['digests'][key]['sha256']
    }
    assert not changed, f'episode {episode}: (golden sum, now) {changed}'
