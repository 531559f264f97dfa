"""Training reports as it goes: TensorBoard event files in the run
directory, and progress lines between evaluations."""

import dataclasses
import pathlib
import struct
import sys

import pytest

pytest.importorskip('sbx', reason='needs robel_dm[learn]')
event_pb2 = pytest.importorskip(
  'tensorboardX.proto.event_pb2', reason='needs robel_dm[learn]'
)

from robel_dm.learning import telemetry  # noqa: E402
from robel_dm.learning import training as learning  # noqa: E402

# Every test trains (the quick tier, -m 'not slow', leaves them out).
pytestmark = pytest.mark.slow

_CONFIG = learning.RunConfig(
  domain='dclaw', task='pose_fixed', steps=1000, eval_every=500,
  eval_episodes=1, hidden=(16, 16),
)  # fmt: skip


def read_events(directory: pathlib.Path) -> dict[str, list[tuple[int, float]]]:
  """Tag -> (step, value) of every summary in the event files (TFRecord
  frames: length, its CRC, the Event, its CRC)."""
  tags = {}
  for path in sorted((directory / telemetry.TENSORBOARD_DIR).glob('events*')):
    data = path.read_bytes()
    at = 0
    while at < len(data):
      (length,) = struct.unpack('<Q', data[at : at + 8])
      event = event_pb2.Event.FromString(data[at + 12 : at + 12 + length])
      at += 12 + length + 4
      for value in event.summary.value:
        tags.setdefault(value.tag, []).append((event.step, value.simple_value))
  return tags


@pytest.fixture(scope='module')
def run(tmp_path_factory):
  output = tmp_path_factory.mktemp('tb')
  lines = []
  original = telemetry.HEARTBEAT_SECONDS
  telemetry.HEARTBEAT_SECONDS = 0.0  # A progress line at every agent dump.
  try:
    history = learning.train(_CONFIG, output, log=lines.append)
  finally:
    telemetry.HEARTBEAT_SECONDS = original
  return output, history, lines


def test_a_run_writes_tensorboard_events(run):
  output, history, _ = run
  tags = read_events(output)
  # Every evaluation, from the untrained policy at step 0 on.
  steps = [row['env_steps'] for row in history]
  assert steps[0] == 0
  for name in ('success_rate', 'mean_score', 'mean_return',
               'violations_position', 'violations_velocity'):  # fmt: skip
    assert [s for s, _ in tags[f'eval/{name}']] == steps, name
  assert [v for _, v in tags['eval/mean_score']] == pytest.approx(
    [row['mean_score'] for row in history]
  )
  # The agent's own values as it learns, and the speed.
  for name in ('train/actor_loss', 'train/critic_loss', 'train/ent_coef',
               'speed/env_steps_per_second'):  # fmt: skip
    assert tags[name] and all(0 < s <= 1000 for s, _ in tags[name]), name
  assert 'config/text_summary' in tags


def test_progress_lines_appear_between_evaluations(run):
  _, history, lines = run
  progress = [line for line in lines if 'of 1000 steps' in line]
  assert progress and 'steps/s' in progress[0]
  evaluations = [line for line in lines if 'success' in line]
  assert len(evaluations) == len(history)
  # A progress line came before the last evaluation's line.
  assert lines.index(progress[0]) < lines.index(evaluations[-1])


def test_without_tensorboardx_a_run_says_so_and_trains(tmp_path, monkeypatch):
  monkeypatch.setitem(sys.modules, 'tensorboardX', None)  # Not installed.
  lines = []
  config = dataclasses.replace(_CONFIG, steps=200, eval_every=200)
  history = learning.train(config, tmp_path, log=lines.append)
  assert len(history) == 2
  assert any('TensorBoard logs are off' in line for line in lines)
  assert not (tmp_path / telemetry.TENSORBOARD_DIR).exists()


def test_tensorboard_itself_reads_the_losses(run):
  # What `tensorboard --logdir` shows (the tensorboard extra): TensorBoard's
  # own reader, not the test's, finds the evaluations and the losses.
  accumulator = pytest.importorskip(
    'tensorboard.backend.event_processing.event_accumulator',
    reason='needs robel_dm[tensorboard]',
  )
  output, history, _ = run
  (events,) = (output / 'tensorboard').glob('events.out.tfevents.*')
  reader = accumulator.EventAccumulator(str(events))
  reader.Reload()
  scalars = set(reader.Tags()['scalars'])
  assert {'eval/success_rate', 'train/actor_loss', 'train/critic_loss',
          'train/ent_coef'} <= scalars  # fmt: skip
  assert len(reader.Scalars('eval/success_rate')) == len(history)
