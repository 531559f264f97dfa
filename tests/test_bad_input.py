"""Bad input to `robel-evaluate` (`python -m robel_dm.commands.evaluate`)
gets one clear line before anything is built (issue 17: policy files,
--output, --tracker), and a printed episode row is always in --output.

The command's main() runs in this process (flags parsed as on the command
line), so that `suite.load` can be watched: a refused run builds no
environment.
"""

import builtins
import errno
import json
import os

from absl import flags
import numpy as np
import pytest

from robel_dm import policies
from robel_dm.evaluation import checks, cli, table
from robel_dm.hardware.tracking import spec as tracker_spec

FLAGS = flags.FLAGS
_TASK = ('dclaw', 'pose_fixed')
_KEYS = ('qpos', 'last_action', 'qpos_error')  # 27 values; 9 actions.


@pytest.fixture
def run_main(evaluate_flags, capsys):
  """Runs the command's main() with command-line flags; returns its exit
  code, stdout and stderr."""

  def run(*argv):
    FLAGS.unparse_flags()
    FLAGS(['evaluate', *argv])
    code = cli.main(['evaluate'])
    out, err = capsys.readouterr()
    return code, out, err

  yield run
  FLAGS.unparse_flags()


def _assert_one_line_error(code, out, err, *names):
  assert code == 2, err
  lines = err.strip().splitlines()
  assert len(lines) == 1 and lines[0].startswith('error: '), err
  for name in names:
    assert str(name) in lines[0]
  assert not out  # No episode ran.


def _policy(inputs=27, hidden=8, outputs=9, keys=_KEYS) -> policies.NumpyPolicy:
  rng = np.random.default_rng(0)
  return policies.NumpyPolicy(
    [rng.normal(size=(hidden, inputs)), rng.normal(size=(outputs, hidden))],
    [rng.normal(size=hidden), rng.normal(size=outputs)],
    'relu',
    'tanh',
    {
      'domain': _TASK[0],
      'task': _TASK[1],
      'task_kwargs': {},
      'observation_keys': list(keys),
      'algo': 'sac',
    },
  )


def _write(policy, path):
  policy.save(path)
  return path


# --- Item 6: policy files ----------------------------------------------------


def _empty(path):
  path.write_bytes(b'')


def _truncated_half(path):
  _policy().save(path)
  data = path.read_bytes()
  path.write_bytes(data[: len(data) // 2])


def _truncated_tail(path):  # The zip's central directory cut short.
  _policy().save(path)
  path.write_bytes(path.read_bytes()[:-10])


def _corrupt_member(path):  # A flipped byte: the member's checksum fails.
  _policy().save(path)
  data = bytearray(path.read_bytes())
  offset = data.index(b'weight_0.npy') + 200
  data[offset] ^= 0xFF
  path.write_bytes(bytes(data))


def _not_an_archive(path):
  path.write_text('this is not a policy\n')


def _a_single_array(path):  # np.save's .npy, named .npz.
  with open(path, 'wb') as file:
    np.save(file, np.zeros((9, 27)))


def _mismatched_bias(path):
  policy = _policy()
  arrays = {
    'activation': 'relu',
    'output': 'tanh',
    'metadata': json.dumps(policy.metadata),
    'weight_0': np.zeros((8, 27)),
    'bias_0': np.zeros(5),
    'weight_1': np.zeros((9, 8)),
    'bias_1': np.zeros(9),
  }
  np.savez(path, **arrays)


def _nan_weights(path):
  with np.load(_write(_policy(), path.with_name('ok.npz'))) as data:
    arrays = dict(data)
  arrays['weight_1'] = np.full_like(arrays['weight_1'], np.nan)
  np.savez(path, **arrays)


@pytest.mark.parametrize(
  'damage',
  [
    _empty,
    _truncated_half,
    _truncated_tail,
    _corrupt_member,
    _not_an_archive,
    _a_single_array,
    _mismatched_bias,
    _nan_weights,
  ],
  ids=lambda damage: damage.__name__.strip('_'),
)
def test_a_damaged_policy_file_is_one_line_before_anything_is_built(
  damage, run_main, built, tmp_path
):
  path = tmp_path / 'policy.npz'
  damage(path)
  code, out, err = run_main(
    f'--policy={path}', '--domain=dclaw', '--task=pose_fixed', '--episodes=1'
  )
  _assert_one_line_error(code, out, err, path)
  assert not built


@pytest.mark.parametrize(
  'policy, message',
  [
    (_policy(inputs=30),
     'takes 30 observation values, dclaw/pose_fixed gives 27'),
    (_policy(outputs=12), 'gives 12 actions, dclaw/pose_fixed takes 9'),
  ],
  ids=['observation_size', 'action_size'],
)  # fmt: skip
def test_a_policy_of_other_sizes_is_refused_before_the_robot_resets(
  policy, message, run_main, built, tmp_path
):
  path = _write(policy, tmp_path / 'policy.npz')
  code, out, err = run_main(
    f'--policy={path}', '--domain=dclaw', '--task=pose_fixed', '--episodes=1'
  )
  _assert_one_line_error(code, out, err, path, message)
  assert not built  # No environment: nothing reset, nothing moved.


def test_a_sweep_checks_every_task_policy_before_the_first_runs(
  run_main, built, tmp_path
):
  # Trained on pose_fixed: the sweep's other tasks cannot use it.
  path = _write(_policy(), tmp_path / 'policy.npz')
  code, out, err = run_main(
    f'--policy={path}', '--domain=dclaw', '--task=all', '--episodes=1'
  )
  _assert_one_line_error(code, out, err, path, 'trained on dclaw/pose_fixed')
  assert not built


@pytest.mark.slow
@pytest.mark.parametrize('device', ['', ' '])
def test_an_empty_device_path_is_refused_not_simulated(run_main, device):
  # As `--device_path=$(head -1 bus.txt)` gives before the bus prints.
  code, out, err = run_main(
    '--domain=dclaw', '--task=pose_fixed', '--episodes=1',
    f'--device_path={device}',
  )  # fmt: skip
  _assert_one_line_error(code, out, err, '--device_path is empty')


def test_a_sound_policy_file_still_runs(run_main, tmp_path):
  path = _write(_policy(), tmp_path / 'policy.npz')
  output = tmp_path / 'results.json'
  code, out, err = run_main(
    f'--policy={path}', '--domain=dclaw', '--task=pose_fixed',
    '--episodes=1', f'--output={output}',
  )  # fmt: skip
  assert code == 0, err
  assert json.loads(output.read_text())['episodes'] == 1


# --- Item 7: --output --------------------------------------------------------


def _directory(path):
  path.mkdir()


def _symlink_to_a_file(path):
  target = path.with_name('elsewhere.json')
  target.write_text('{"kept": true}')
  path.symlink_to(target)


def _dangling_symlink(path):
  path.symlink_to(path.with_name('nowhere.json'))


def _fifo(path):
  os.mkfifo(path)


@pytest.mark.parametrize(
  'make, kind',
  [
    (_directory, 'is a directory'),
    (_symlink_to_a_file, 'is a symbolic link'),
    (_dangling_symlink, 'is a symbolic link'),
    (_fifo, 'is a fifo'),
  ],
  ids=lambda value: getattr(value, '__name__', '').strip('_'),
)
def test_an_output_that_is_not_a_regular_file_is_refused_up_front(
  make, kind, run_main, built, tmp_path
):
  path = tmp_path / 'results.json'
  make(path)
  before = os.lstat(path)
  code, out, err = run_main(
    '--policy=zero', '--task=pose_fixed', '--episodes=1', f'--output={path}'
  )
  _assert_one_line_error(code, out, err, path, kind)
  assert not built
  after = os.lstat(path)  # Left as it was, not replaced by a file.
  assert (after.st_mode, after.st_ino) == (before.st_mode, before.st_ino)
  if path.is_symlink() and path.exists():
    assert json.loads(path.read_text()) == {'kept': True}


@pytest.mark.parametrize('device', ['/dev/full', '/dev/null'])
def test_a_device_output_is_refused(device):
  # Called directly: a run that wrongly accepted it would replace the
  # device node (these tests may run as root).
  if not os.path.exists(device):
    pytest.skip(f'no {device}')
  with pytest.raises(ValueError, match=f'--output: {device} is a device'):
    checks.check_output(device)


def test_an_output_path_naming_a_folder_is_refused(tmp_path):
  with pytest.raises(ValueError, match='names a folder'):
    checks.check_output(f'{tmp_path}/results/')


class _FullDisk:
  """A file on a full disk (as /dev/full): every write fails."""

  def __init__(self, file):
    self._file = file

  def write(self, text):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

  def __getattr__(self, name):
    return getattr(self._file, name)

  def __enter__(self):
    return self

  def __exit__(self, *exc_info):
    self._file.close()


@pytest.mark.slow
def test_a_failed_write_is_one_line_and_keeps_the_finished_episodes(
  run_main, monkeypatch, tmp_path
):
  # The disk fills once the first episode is saved: the results writer's
  # later files (its *.partial files) take no bytes.
  real_open = open
  partial_files = []

  def open_on_a_filling_disk(file, mode='r', *args, **kwargs):
    handle = real_open(file, mode, *args, **kwargs)
    if not str(file).endswith('.partial'):
      return handle
    partial_files.append(file)
    return handle if len(partial_files) == 1 else _FullDisk(handle)

  monkeypatch.setattr(builtins, 'open', open_on_a_filling_disk)
  output = tmp_path / 'results.json'
  code, out, err = run_main(
    '--policy=zero', '--task=pose_fixed', '--episodes=3', f'--output={output}'
  )
  monkeypatch.undo()
  assert len(partial_files) == 2  # Episode 0 saved; episode 1's save failed.
  assert code == 2, err
  lines = err.strip().splitlines()
  assert len(lines) == 1, err
  assert 'No space left on device' in lines[0] and str(output) in lines[0]
  assert 'keeps the 1 episode' in lines[0]
  saved = json.loads(output.read_text())  # Whole, as saved after episode 0.
  assert saved['episodes'] == len(saved['records']) == 1
  rows = [line for line in out.splitlines() if line[:7].strip().isdigit()]
  assert rows == [table.format_row(0, saved['records'][0])]
  assert [p.name for p in tmp_path.iterdir()] == ['results.json']


def test_the_json_writer_keeps_the_previous_file_when_a_write_fails(
  monkeypatch, tmp_path
):
  path = tmp_path / 'results.json'
  checks.write_json(str(path), {'episodes': 1})
  real_open = open
  monkeypatch.setattr(
    builtins,
    'open',
    lambda *args, **kwargs: _FullDisk(real_open(*args, **kwargs)),
  )
  with pytest.raises(OSError, match='No space left'):
    checks.write_json(str(path), {'episodes': 2})
  monkeypatch.undo()
  assert json.loads(path.read_text()) == {'episodes': 1}
  assert [p.name for p in tmp_path.iterdir()] == ['results.json']  # No debris.


# --- Item 8: --tracker -------------------------------------------------------


@pytest.mark.parametrize(
  'spec, message',
  [
    ('natnet:H,rigid_body=1,data_port=70000', "data_port '70000'"),
    ('natnet:H,rigid_body=1,data_port=-1', "data_port '-1'"),
    ('natnet:H,rigid_body=1,data_port=0', "data_port '0'"),
    ('natnet:H,rigid_body=1,data_port=15x', "data_port '15x'"),
    ('natnet:H:70000,rigid_body=1', "bad port '70000'"),
    ('natnet:H:0,rigid_body=1', "bad port '0'"),
    ('natnet:H:,rigid_body=1', "bad port ''"),
    ('natnet:999.1.1.1,rigid_body=1', "server '999.1.1.1'"),
    ('natnet:239.255.42.99,rigid_body=1', "server '239.255.42.99'"),
    ('natnet:bad_host!,rigid_body=1', "server 'bad_host!'"),
    ('natnet:H,rigid_body=1,multicast=notanip', "multicast 'notanip'"),
    ('natnet:H,rigid_body=1,multicast=10.0.0.5', "multicast '10.0.0.5'"),
    ('natnet:H,rigid_body=1,local=999.1.1.1', "local '999.1.1.1'"),
    ('natnet:H,rigid_body=1,local=localhost', "local 'localhost'"),
    ('natnet:H,rigid_body=1,local=239.1.1.1', "local '239.1.1.1'"),
    ('natnet:H,rigid_body=0', "rigid_body '0'"),
    ('natnet:H,rigid_body=-3', "rigid_body '-3'"),
    ('natnet:H,rigid_body=torso', "rigid_body 'torso'"),
    ('natnet:H,rigid_body=99999999999', "rigid_body '99999999999'"),
    ('natnet:H,rigid_body=1,target=1.5', "target '1.5'"),
    ('natnet:H,rigid_body=1,heading=', "heading ''"),
    ('natnet:H,rigid_body=1,version=5.0', "version '5.0'"),
    ('natnet:H,rigid_body=1,version=four', "version 'four'"),
    ('natnet:H,rigid_body=1,y_up=maybe', "y_up 'maybe'"),
    ('natnet:H,rigid_body=1,colour=red', "unknown option 'colour=red'"),
    ('natnet:H,rigid_body=1,rigid_body=2', 'rigid_body is given twice'),
    ('natnet:H,rigid_body=1,target', 'option target needs a value'),
  ],
)  # fmt: skip
def test_every_tracker_field_is_checked(spec, message):
  with pytest.raises(tracker_spec.TrackerSpecError) as raised:
    tracker_spec.parse(spec)
  text = str(raised.value)
  assert message in text and '\n' not in text


def test_good_tracker_fields_parse():
  fields = tracker_spec.parse(
    'natnet:10.0.0.5:1600,rigid_body=01,target=2,heading=3,'
    'multicast=239.255.42.99,data_port=1512,local=10.0.0.2,version=4,'
    'y_up=false'
  )
  assert fields == {
    'server': '10.0.0.5', 'command_port': 1600, 'rigid_body': 1,
    'target': 2, 'heading': 3, 'multicast': '239.255.42.99',
    'data_port': 1512, 'local': '10.0.0.2', 'version': (4, 0),
    'y_up': False,
  }  # fmt: skip
  unicast = tracker_spec.parse(
    'natnet:motive.lab,rigid_body=1,multicast=unicast,data_port=0'
  )
  assert unicast['server'] == 'motive.lab' and unicast['data_port'] == 0


@pytest.mark.parametrize(
  'option, message',
  [
    ('data_port=70000', "data_port '70000'"),
    ('multicast=notanip', "multicast 'notanip'"),
    ('local=999.1.1.1', "local '999.1.1.1'"),
  ],
)
def test_a_bad_tracker_flag_is_one_line_before_anything_is_built(
  option, message, run_main, built
):
  code, out, err = run_main(
    '--domain=dkitty', '--task=stand_fixed', '--policy=zero',
    '--episodes=1', '--device_path=virtual',
    f'--tracker=natnet:127.0.0.1,rigid_body=1,{option}',
  )  # fmt: skip
  _assert_one_line_error(code, out, err, message)
  assert not built


# --- Item 12a: a printed row is a saved row ----------------------------------


@pytest.mark.slow
@pytest.mark.parametrize('workers', [1, 2])
def test_ctrl_c_after_a_row_is_printed_finds_it_saved(
  workers, run_main, monkeypatch, tmp_path
):
  # Ctrl-C lands right after the first episode's row is printed.
  printed = []

  def print_then_interrupt(*args, **kwargs):
    print(*args, **kwargs)
    text = ' '.join(map(str, args))
    if text.split() and text.split()[0].isdigit():  # An episode's row.
      printed.append(text)
      raise KeyboardInterrupt

  monkeypatch.setattr(cli, 'print', print_then_interrupt, raising=False)
  output = tmp_path / 'results.json'
  code, _, _ = run_main(
    '--policy=zero', '--task=pose_fixed', '--episodes=2',
    f'--workers={workers}', f'--output={output}',
  )  # fmt: skip
  assert code == 130
  assert len(printed) == 1
  saved = json.loads(output.read_text())
  rows = [table.format_row(i, r) for i, r in enumerate(saved['records'])]
  assert printed == rows[: len(printed)]


@pytest.mark.slow
def test_a_policy_runs_on_another_variant_only_when_asked(run_main):
  path = policies.baseline_path('dclaw', 'pose_fixed')
  argv = ('--domain=dclaw', '--task=pose_random', f'--policy={path}',
          '--episodes=1')  # fmt: skip
  code, _, err = run_main(*argv)
  assert code == 2 and '--allow_other_variant' in err
  code, out, _ = run_main(*argv, '--allow_other_variant')
  assert code == 0 and 'success rate' in out
  # Another family of tasks stays refused.
  code, _, err = run_main(
    '--domain=dclaw', '--task=turn_random', f'--policy={path}',
    '--allow_other_variant',
  )  # fmt: skip
  assert code == 2 and 'trained on dclaw/pose_fixed' in err


@pytest.mark.parametrize(
  ('flags', 'message'),
  [
    (['--camera=front'], '--camera needs --video'),
    (['--allow_other_seed'], '--allow_other_seed needs --policy=replay'),
    (['--allow_other_variant'], '--allow_other_variant needs a policy file'),
  ],
)
def test_a_flag_that_would_do_nothing_is_refused(run_main, flags, message):
  code, _, err = run_main('--policy=zero', '--episodes=1', *flags)
  assert code == 2 and message in err
