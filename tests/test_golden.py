"""Every task reproduces its golden trajectories bit for bit (see golden.py).

A failure names the first step that differs and the quantities that
changed, with their episode sums. If the change is deliberate, regenerate
the file with `python tests/golden.py` and say why in the commit.
"""

import json

import golden
import pytest

_GOLDEN = json.loads(golden.PATH.read_text())
_CONFIGS = golden.configurations()


def test_every_configuration_is_pinned():
  assert sorted(_GOLDEN) == sorted(golden.name(*c) for c in _CONFIGS)


# The quick tier (-m 'not slow') checks the first configuration only.
@pytest.mark.parametrize(
  'config',
  [
    pytest.param(c, marks=() if i == 0 else pytest.mark.slow)
    for i, c in enumerate(_CONFIGS)
  ],
  ids=[golden.name(*c) for c in _CONFIGS],
)
def test_trajectories_match_bit_for_bit(config):
  expected = _GOLDEN[golden.name(*config)]
  actual = golden.record(*config)
  for episode, (want, got) in enumerate(zip(expected, actual, strict=True)):
    first = next(
      (
        step
        for step, (a, b) in enumerate(
          zip(want['step_digests'], got['step_digests'], strict=False)
        )
        if a != b
      ),
      None,
    )
    where = f'episode {episode}, first different at step {first}'
    assert got['steps'] == want['steps'], f'{where}: length'
    assert sorted(got['digests']) == sorted(want['digests']), where
    changed = {
      key: (want['digests'][key]['sum'], value['sum'])
      for key, value in got['digests'].items()
      if value['sha256'] != want['digests'][key]['sha256']
    }
    assert not changed, f'{where}: (golden sum, now) {changed}'
