"""Loads an exported dataset with LeRobot's own LeRobotDataset.

Not part of the test suite: LeRobot pins an older torch than the `learn`
extra, so this runs in a separate environment holding `lerobot`
(docs/recording.md says how). Usage:

  python tests/external/load_with_lerobot.py DATASET_DIR

(LeRobot 0.4 and later read v3.0 exports, LeRobot 0.3 v2.1 ones.)

Prints what it checked; exits non-zero at the first failed check.
"""

import json
import pathlib
import sys

from lerobot.datasets.lerobot_dataset import LeRobotDataset
import numpy as np
import torch


def main(root: pathlib.Path) -> None:
  info = json.loads((root / 'meta/info.json').read_text())
  fps = info['fps']
  dataset = LeRobotDataset('robel_dm/export', root=root)
  print(
    f'lerobot loaded {root}: {dataset.num_episodes} episodes, '
    f'{dataset.num_frames} frames, fps {dataset.fps}'
  )
  assert dataset.num_episodes == info['total_episodes']
  assert len(dataset) == info['total_frames']
  frame = dataset[0]
  task = frame['task']
  print(f'frame 0: task {task!r}, keys {len(frame)}')
  assert task == 'dclaw/turn_fixed' or '/' in task
  for name, feature in info['features'].items():
    value = frame[name]
    if feature['shape'] == [1]:
      assert value.shape == (), (name, value.shape)  # a scalar, not [x]
    else:
      assert tuple(value.shape) == tuple(feature['shape']), name
  # Wall-clock offsets survive LeRobot's float32 tensors, step by step.
  times = [dataset[i]['wall_time_elapsed'].item() for i in range(5)]
  assert times[0] == 0 and np.all(np.diff(times) > 0), times
  print(
    f'wall_time_elapsed ({frame["wall_time_elapsed"].dtype}): first '
    f'steps {np.diff(times).round(4)} s apart'
  )
  loader = torch.utils.data.DataLoader(dataset, batch_size=16, shuffle=True)
  batch = next(iter(loader))
  assert batch['action'].shape[0] == 16
  print(f'DataLoader batch: action {tuple(batch["action"].shape)}')
  shifted = LeRobotDataset(
    'robel_dm/export',
    root=root,
    delta_timestamps={'action': [0.0, 1 / fps, 2 / fps]},
  )
  window = shifted[1]['action']
  torch.testing.assert_close(window[0], dataset[1]['action'])
  torch.testing.assert_close(window[1], dataset[2]['action'])
  print(
    f'delta_timestamps: action window {tuple(window.shape)} matches '
    'the next frames'
  )
  if info['codebase_version'] == 'v2.1':
    last = int(dataset.episode_data_index['to'][0]) - 1
  else:
    last = dataset.meta.episodes[0]['dataset_to_index'] - 1
  end = shifted[last]
  assert end['action_is_pad'].tolist() == [False, True, True]
  print('episode ends are padded')
  print('all checks passed')


if __name__ == '__main__':
  main(pathlib.Path(sys.argv[1]))
