"""The viewer command explains why it cannot open a window."""

import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

from robel_dm.commands import view


@pytest.mark.parametrize('backend', ['egl', 'osmesa'])
def test_offscreen_backends_are_explained(backend):
  with pytest.raises(ValueError, match='MUJOCO_GL=glfw'):
    view.check_display({'MUJOCO_GL': backend, 'DISPLAY': ':0'})


def test_a_missing_display_is_explained():
  with pytest.raises(ValueError, match='no display'):
    view.check_display({'MUJOCO_GL': 'glfw'})
  view.check_display({'MUJOCO_GL': 'glfw', 'DISPLAY': ':0'})  # Fine.


@pytest.mark.slow
def test_the_command_fails_with_one_clear_line_without_a_display():
  env = {k: v for k, v in os.environ.items() if k != 'DISPLAY'}
  env['MUJOCO_GL'] = 'egl'
  result = subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.view', '--task=turn_fixed'],
    capture_output=True, text=True, env=env, check=False,
  )  # fmt: skip
  assert result.returncode == 2
  assert result.stderr.startswith('error: MUJOCO_GL=egl renders offscreen')
  assert 'Traceback' not in result.stderr


@pytest.mark.skipif(
  not shutil.which('xvfb-run'), reason='needs xvfb-run (a virtual display)'
)
def test_the_viewer_opens_and_runs_a_policy_on_a_virtual_display():
  env = {k: v for k, v in os.environ.items() if k != 'MUJOCO_GL'}
  process = subprocess.Popen(
    ['xvfb-run', '-a', '-s', '-screen 0 1024x768x24', sys.executable, '-m',
     'robel_dm.commands.view', '--domain=dclaw', '--task=pose_fixed',
     '--policy=reference'],
    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    start_new_session=True,
  )  # fmt: skip
  try:
    time.sleep(10)
    assert process.poll() is None, process.communicate()[1]  # Still open.
  finally:
    os.killpg(process.pid, signal.SIGKILL)  # xvfb-run, Xvfb and the viewer.
    process.communicate(timeout=20)


@pytest.mark.slow
def test_a_replay_that_is_no_recording_is_one_line(tmp_path):
  # The display is taken as given: the policy fails before any window.
  program = (
    'import sys; from absl import app; from robel_dm.commands import view; '
    'view.check_display = lambda: None; '
    f"sys.argv = ['view', '--task=pose_fixed', '--policy=replay:{tmp_path}']; "
    'view._define_flags(); app.run(view.main)'
  )
  result = subprocess.run(
    [sys.executable, '-c', program], capture_output=True, text=True,
    env={**os.environ, 'MUJOCO_GL': 'egl'}, timeout=120,
  )  # fmt: skip
  assert result.returncode == 2, result.stderr
  (line,) = result.stderr.strip().splitlines()
  assert line.startswith('error: ') and str(tmp_path) in line
