"""Random bit flips in recording files: the reader names or survives each.

Records, for each robot (D'Claw Turn Fixed and D'Kitty Stand Fixed in
simulation, with `--virtual` also D'Claw Turn Fixed on the in-process
virtual bus, whose rows carry the motor columns), a directory holding one
finished episode and one being recorded (its stream in batches of 4 or 5
rows), then flips one random bit at a time (seeded) in one of its files, in
turn:

  stream          the in-progress episode's Arrow stream
  parquet         the finished episode's Parquet file (its episodes.jsonl
                  line, with the file's SHA-256, in place)
  parquet_alone   the same file without its line (a kill before the line,
                  or a line lost): only the file's own checks apply

and reads the directory with `recording.read` in a child process (a crash
is a failure that names the flip). Each flip must end in one of

  named       a warning names the flipped file, the other episode reads as
              before, and what is read of the flipped one is exactly a
              prefix of its rows (a stream) or nothing (a Parquet file)
  unchanged   no warning, and everything reads exactly as before (a flip
              in padding or in bytes the reader does not use)

Anything else (an exception, a crash, a changed value read without a
warning, a damaged row returned) is a failure, printed with its flip.

    MUJOCO_GL=egl python benchmarks/recording_damage.py [--flips 1000]
        [--seed 0] [--virtual] [--dir DIR]
"""

import argparse
import collections
import json
import pathlib
import shutil
import subprocess
import sys
import tempfile
import warnings

import numpy as np

KINDS = ('stream', 'parquet', 'parquet_alone')
ROBOTS = {
  'dclaw': ('dclaw', 'turn_fixed', None),
  'dkitty': ('dkitty', 'stand_fixed', None),
  'dclaw_virtual': ('dclaw', 'turn_fixed', 'virtual'),
}
STREAM_BATCH = 4  # Rows per record batch of the in-progress stream.
STREAM_STEPS = 15  # Steps of the in-progress episode.


def _record(directory: pathlib.Path, robot: str) -> None:
  """A finished episode and a copy of the next one in progress."""
  from robel_dm import recording, suite  # noqa: PLC0415
  from robel_dm.recording import format as format_lib  # noqa: PLC0415

  domain, task, device = ROBOTS[robot]
  interval = format_lib.FLUSH_INTERVAL
  format_lib.FLUSH_INTERVAL = 1e9  # Batches as flush() makes them.
  robot_options = suite.RobotOptions(device) if device else None  # Sim.
  env = suite.load(domain, task, seed=0, robot=robot_options)
  env = recording.Recorder(
    env, directory / 'live', metadata={'domain': domain, 'task': task}
  )
  rng = np.random.default_rng(0)
  size = env.action_spec().shape[0]
  try:
    timestep = env.reset()
    while not timestep.last():
      timestep = env.step(rng.uniform(-1, 1, size))
    env.reset()
    for step in range(STREAM_STEPS):
      env.step(rng.uniform(-1, 1, size))
      if step % STREAM_BATCH == STREAM_BATCH - 1:
        env._writer.flush()  # noqa: SLF001 (batches of a known size)
    env._writer.flush()  # noqa: SLF001
    shutil.copytree(directory / 'live', directory / 'pristine')
  finally:
    env.close()
    format_lib.FLUSH_INTERVAL = interval
  shutil.rmtree(directory / 'live')


def _files(directory: pathlib.Path) -> dict[str, pathlib.Path]:
  from robel_dm.recording import format as format_lib  # noqa: PLC0415

  files = format_lib.episode_files(directory)
  return {
    'stream': files[1]['arrows'],
    'parquet': files[0]['parquet'],
    'parquet_alone': files[0]['parquet'],
  }


def _read(directory: pathlib.Path):
  """Episode index -> (metadata, steps); and the warnings' messages."""
  from robel_dm import recording  # noqa: PLC0415

  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter('always')
    episodes = recording.read(directory)
  read = {e.metadata['episode_index']: (e.metadata, e.steps) for e in episodes}
  return read, [str(w.message) for w in caught]


def _same(steps: dict, reference: dict, rows: int | None = None) -> bool:
  """Whether `steps` are `reference`'s (its first `rows` rows), exactly."""
  if set(steps) != set(reference):
    return False
  for name, values in steps.items():
    expected = reference[name][:rows]
    if values.dtype != expected.dtype or values.shape != expected.shape:
      return False
    if not np.array_equal(values, expected, equal_nan=values.dtype.kind == 'f'):
      return False
  return True


def _outcome(kind, path, read, messages, reference) -> str:
  """The flip's outcome: 'named', 'unchanged' or what went wrong."""
  flipped = 1 if kind == 'stream' else 0
  other = 1 - flipped
  if other not in read or not _same(read[other][1], reference[other][1]):
    return 'the other episode changed'
  named = [m for m in messages if str(path) in m]
  if len(named) != len(messages):
    return f'a warning names another file: {messages}'
  if flipped not in read:
    return 'named' if named else 'the episode vanished without a warning'
  metadata, steps = read[flipped]
  if not named:
    same = _same(steps, reference[flipped][1])
    same = same and metadata == reference[flipped][0]
    return 'unchanged' if same else 'a changed episode read without a warning'
  if kind != 'stream':
    return 'a damaged Parquet file was read'
  rows = len(next(iter(steps.values())))
  expected = {**reference[flipped][0], 'length': rows}
  if metadata != expected or not _same(steps, reference[flipped][1], rows):
    return 'damaged rows of a stream were read'
  return 'named'


def _prepare(pristine: pathlib.Path, work: pathlib.Path, kind: str) -> None:
  """`work`, a copy of `pristine` as `kind` needs it."""
  from robel_dm.recording import format as format_lib  # noqa: PLC0415

  shutil.rmtree(work, ignore_errors=True)
  shutil.copytree(pristine, work)
  if kind == 'parquet_alone':
    (work / format_lib.EPISODES).unlink()


def _child(root: pathlib.Path, flips: int, seed: int, robots) -> None:
  """Flips bits; prints each flip before reading, and its outcome after."""
  rng = np.random.default_rng(seed)
  work = root / 'work'
  references = {}
  for robot in robots:
    for kind in KINDS:
      _prepare(root / robot / 'pristine', work, kind)
      read, messages = _read(work)
      assert not messages, messages  # Undamaged: no warning.
      references[robot, kind] = read
  for flip in range(flips):
    robot = robots[flip % len(robots)]
    kind = KINDS[flip // len(robots) % len(KINDS)]
    _prepare(root / robot / 'pristine', work, kind)
    path = _files(work)[kind]
    data = bytearray(path.read_bytes())
    position, bit = int(rng.integers(len(data))), int(rng.integers(8))
    data[position] ^= 1 << bit
    path.write_bytes(bytes(data))
    flip_line = {'flip': flip, 'robot': robot, 'kind': kind,
                 'byte': position, 'of': len(data), 'bit': bit}  # fmt: skip
    print(json.dumps(flip_line), flush=True)
    try:
      read, messages = _read(work)
      outcome = _outcome(kind, path, read, messages, references[robot, kind])
    except Exception as error:  # noqa: BLE001 (a failure to report)
      outcome = f'{type(error).__name__}: {error}'
    print(json.dumps({'flip': flip, 'outcome': outcome}), flush=True)


def run(flips: int, seed: int, robots, directory=None) -> dict:
  """Records, flips in a child process, and tallies.

  Returns:
    'counts': robot -> kind -> outcome -> flips; 'failures': the flips
    (robot, kind, byte, bit) that did not end named or unchanged, each
    with its outcome ('crashed: ...' if the child died reading it).
  """
  root = pathlib.Path(
    tempfile.mkdtemp(prefix='recording_damage_', dir=directory)
  )
  try:
    for robot in robots:
      _record(root / robot, robot)
    command = [sys.executable, __file__, '--child', str(root),
               f'--flips={flips}', f'--seed={seed}',
               f'--robots={",".join(robots)}']  # fmt: skip
    child = subprocess.run(command, capture_output=True, text=True)
  finally:
    shutil.rmtree(root, ignore_errors=True)
  counts = collections.defaultdict(collections.Counter)
  failures, pending = [], None
  for line in child.stdout.splitlines():
    entry = json.loads(line)
    if 'outcome' not in entry:
      pending = entry
      continue
    counts[f'{pending["robot"]} {pending["kind"]}'][entry['outcome']] += 1
    if entry['outcome'] not in ('named', 'unchanged'):
      failures.append({**pending, 'outcome': entry['outcome']})
    pending = None
  if child.returncode:
    reason = f'crashed: exit {child.returncode}: {child.stderr[-2000:]}'
    failures.append({**(pending or {}), 'outcome': reason})
  return {'counts': {k: dict(v) for k, v in counts.items()},
          'failures': failures}  # fmt: skip


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--flips', type=int, default=1000)
  parser.add_argument('--seed', type=int, default=0)
  parser.add_argument(
    '--virtual', action='store_true', help='also a virtual-bus recording'
  )
  parser.add_argument('--dir', default=None, help='where recordings go')
  parser.add_argument('--json', action='store_true', help='print JSON only')
  parser.add_argument('--child', help=argparse.SUPPRESS)
  parser.add_argument('--robots', help=argparse.SUPPRESS)
  args = parser.parse_args()
  if args.child:
    _child(pathlib.Path(args.child), args.flips, args.seed,
           args.robots.split(','))  # fmt: skip
    return
  robots = ['dclaw', 'dkitty'] + (['dclaw_virtual'] if args.virtual else [])
  result = run(args.flips, args.seed, robots, args.dir)
  if args.json:
    print(json.dumps(result))
    return
  print(f'{args.flips} bit flips (seed {args.seed}):')
  for name, outcomes in sorted(result['counts'].items()):
    tally = sorted(outcomes.items())
    print(f'  {name:>24}: ' + ', '.join(f'{n} {what}' for what, n in tally))
  print(f'{len(result["failures"])} failures')
  for failure in result['failures']:
    print(f'  {json.dumps(failure)}')
  if result['failures']:
    sys.exit(1)


if __name__ == '__main__':
  main()
