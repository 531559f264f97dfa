"""What recording costs per control step, with fsync on and off.

Runs `--steps` control steps of `suite.load('dclaw', 'turn_fixed', seed=0)`
with uniform random actions (seeded; random data compresses less than a
constant action, so the bytes per row are not flattered; episodes end and
reset as they come) three ways, in one
process and interleaved round by round: without a recorder, recorded with
`format.FSYNC = False`, and recorded with `format.FSYNC = True` (the
default). Each figure is the minimum over rounds of the per-round mean
(other jobs on a shared machine only ever add time). Also prints the bytes
per recorded row (a dm_env timestep) of the finished Parquet files.

    MUJOCO_GL=egl python benchmarks/recording_cost.py [--steps 2000]
        [--rounds 5] [--dir DIR]

`--dir` is where the recordings go (a temporary directory inside it,
removed after): fsync costs what that file system makes it cost.
"""

import argparse
import pathlib
import shutil
import tempfile
import time

import numpy as np

from robel_dm import recording, suite
from robel_dm.recording import format as format_lib


def _run(steps: int, directory: pathlib.Path | None) -> float:
  """Seconds per control step over `steps` steps (resets included)."""
  env = suite.load('dclaw', 'turn_fixed', seed=0)
  if directory is not None:
    env = recording.Recorder(env, directory, metadata={'policy': 'random'})
  spec = env.action_spec()
  actions = np.random.default_rng(0).uniform(
    spec.minimum, spec.maximum, (steps, *spec.shape)
  )
  start = time.perf_counter()
  try:
    timestep = env.reset()
    for action in actions:
      if timestep.last():
        timestep = env.reset()
      timestep = env.step(action)
  finally:
    env.close()  # Finishes the last episode: part of the cost.
  return (time.perf_counter() - start) / steps


def _bytes_per_row(directory: pathlib.Path) -> float:
  files = list((directory / format_lib.CHUNK).glob('*.parquet'))
  rows = sum(len(episode) for episode in recording.read(directory))
  return sum(f.stat().st_size for f in files) / rows


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--steps', type=int, default=2000)
  parser.add_argument('--rounds', type=int, default=5)
  parser.add_argument('--dir', default=None, help='where recordings go')
  args = parser.parse_args()
  root = pathlib.Path(tempfile.mkdtemp(prefix='recording_cost_', dir=args.dir))
  modes = ('no recorder', 'fsync off', 'fsync on')
  times = {mode: [] for mode in modes}
  sizes = []
  try:
    _run(50, None)  # Warm up (imports, model compilation).
    for round_ in range(args.rounds):
      for mode in modes:
        directory = None
        if mode != 'no recorder':
          directory = root / f'{mode.replace(" ", "_")}_{round_}'
          format_lib.FSYNC = mode == 'fsync on'
        times[mode].append(_run(args.steps, directory))
        if directory is not None:
          sizes.append(_bytes_per_row(directory))
          shutil.rmtree(directory)
  finally:
    format_lib.FSYNC = True
    shutil.rmtree(root, ignore_errors=True)
  best = {mode: min(values) * 1e3 for mode, values in times.items()}
  print(
    f'dclaw/turn_fixed, random actions, {args.steps} steps x {args.rounds} '
    f'rounds (min of per-round means), recordings in {root.parent}'
  )
  for mode in modes:
    cost = best[mode] - best['no recorder']
    extra = '' if mode == 'no recorder' else f'  (recording: {cost:.3f} ms)'
    print(f'{mode:>12}: {best[mode]:.3f} ms/step{extra}')
  on, off, plain = best['fsync on'], best['fsync off'], best['no recorder']
  print(f'fsync on / fsync off: {on / off:.3f} per step', end='')
  if off > plain:
    print(f', {(on - plain) / (off - plain):.2f} of the recording cost')
  else:
    print()
  print(
    f'Parquet: {np.mean(sizes):.0f} bytes per row '
    f'(min {min(sizes):.0f}, max {max(sizes):.0f})'
  )


if __name__ == '__main__':
  main()
