"""Training into a directory that already holds a run: refused unless
--resume continues it or --overwrite starts it over."""

import dataclasses
import json
import os
import pathlib
import shutil
import subprocess
import sys

import pytest

pytest.importorskip('stable_baselines3', reason='needs robel_dm[learn]')
pytest.importorskip('sbx', reason='needs robel_dm[learn]')

from robel_dm.learning import robot_training, run_files, telemetry  # noqa: E402
from robel_dm.learning import training as learning  # noqa: E402

QUIET = {'log': lambda line: None}
CONFIG = learning.RunConfig(
  domain='dclaw',
  task='pose_fixed',
  steps=16,
  eval_every=16,
  eval_episodes=1,
  hidden=(16, 16),
)


def _files(directory: pathlib.Path) -> dict[str, bytes]:
  """Every file under `directory` (relative path -> contents)."""
  return {
    str(path.relative_to(directory)): path.read_bytes()
    for path in sorted(directory.rglob('*'))
    if path.is_file()
  }


def _events(directory: pathlib.Path) -> set[str]:
  return {
    path.name
    for path in (directory / telemetry.TENSORBOARD_DIR).glob(
      'events.out.tfevents.*'
    )
  }


@pytest.fixture(scope='module')
def old_run(tmp_path_factory):
  output = tmp_path_factory.mktemp('run')
  learning.train(CONFIG, output, **QUIET)
  return output


@pytest.mark.slow
def test_training_again_without_resume_is_refused_and_leaves_the_run(
  old_run,
):
  before = _files(old_run)
  assert 'eval.jsonl' in before and before['eval.jsonl']
  with pytest.raises(ValueError) as raised:
    learning.train(CONFIG, old_run, **QUIET)
  message = str(raised.value)
  assert str(old_run) in message and '\n' not in message
  assert '--resume' in message and '--overwrite' in message
  assert _files(old_run) == before


@pytest.mark.parametrize(
  'name', ['config.json', 'eval.jsonl', 'checkpoint.zip', 'policy.npz']
)
def test_any_run_file_marks_a_run(tmp_path, name):
  (tmp_path / name).write_text('')
  with pytest.raises(ValueError, match='--resume .*--overwrite'):
    learning.train(CONFIG, tmp_path, **QUIET)
  assert [path.name for path in tmp_path.iterdir()] == [name]


def test_absent_empty_or_unrelated_directories_are_fine(tmp_path):
  learning.check_output_dir(tmp_path / 'absent', False, False)
  learning.check_output_dir(tmp_path, False, False)
  (tmp_path / 'notes.txt').write_text('mine')
  (tmp_path / telemetry.TENSORBOARD_DIR).mkdir()
  learning.check_output_dir(tmp_path, False, False)


@pytest.mark.slow
def test_overwrite_starts_over(old_run, tmp_path):
  output = tmp_path / 'run'
  shutil.copytree(old_run, output)
  (output / 'notes.txt').write_text('mine')
  old_events = _events(output)
  assert old_events
  # Event files are named by the second they were opened in, so a new one
  # can take an old one's name: mark the old ones' contents instead.
  tensorboard = output / 'tensorboard'
  for name in old_events:
    with open(tensorboard / name, 'ab') as file:
      file.write(b'OLD RUN')
  old_log = (output / learning.EVAL_LOG).read_text()
  config = dataclasses.replace(CONFIG, seed=1)
  history = learning.train(config, output, overwrite=True, **QUIET)
  rows = [
    json.loads(line)
    for line in (output / learning.EVAL_LOG).read_text().splitlines()
  ]
  assert rows == json.loads(json.dumps(history))
  assert [row['env_steps'] for row in rows] == [0, 16]
  assert (output / learning.EVAL_LOG).read_text() != old_log
  assert json.loads((output / learning.CONFIG).read_text())['seed'] == 1
  new_events = _events(output)
  assert len(new_events) == 1
  assert b'OLD RUN' not in (tensorboard / new_events.pop()).read_bytes()
  assert (output / 'notes.txt').read_text() == 'mine'


@pytest.mark.slow
def test_resume_and_overwrite_together_are_refused(old_run, tmp_path):
  before = _files(old_run)
  for output in (old_run, tmp_path):
    with pytest.raises(ValueError, match='--resume .*--overwrite'):
      learning.train(CONFIG, output, resume=True, overwrite=True, **QUIET)
  assert _files(old_run) == before
  assert not any(tmp_path.iterdir())


def test_clearing_removes_only_the_runs_files(tmp_path):
  names = run_files.RUN_FILES + (
    robot_training.PROGRESS_LOG,
    robot_training.ROBOT,
  )
  for name in names:
    (tmp_path / name).write_text('old')
  (tmp_path / robot_training.RECORDING / 'meta').mkdir(parents=True)
  events = tmp_path / telemetry.TENSORBOARD_DIR
  events.mkdir()
  (events / 'events.out.tfevents.1.host').write_text('old')
  (events / 'notes.txt').write_text('mine')
  (tmp_path / 'notes.txt').write_text('mine')
  learning.clear_output_dir(tmp_path, names + (robot_training.RECORDING,))
  assert _files(tmp_path) == {
    'notes.txt': b'mine',
    f'{telemetry.TENSORBOARD_DIR}/notes.txt': b'mine',
  }
  assert not (tmp_path / robot_training.RECORDING).exists()


@pytest.mark.slow
@pytest.mark.parametrize(
  'flags, message',
  [
    ([], 'already holds a run'),
    (['--device_path=virtual'], 'already holds a run'),
    (['--resume', '--overwrite'], '--resume continues a run'),
  ],
)
def test_the_command_line_says_so_in_one_line(old_run, flags, message):
  before = _files(old_run)
  result = subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.train', f'--output_dir={old_run}',
     '--steps=16', '--eval_every=16', '--eval_episodes=1', *flags],
    capture_output=True, text=True, timeout=300,
    env={**os.environ, 'MUJOCO_GL': 'egl'},
  )  # fmt: skip
  assert result.returncode == 2, result.stderr
  last = result.stderr.strip().splitlines()[-1]
  assert last.startswith('error: ') and message in last
  assert '--resume' in last and '--overwrite' in last
  assert _files(old_run) == before
