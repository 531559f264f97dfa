"""robel_dm picks an offscreen OpenGL backend when nothing asked for one and
there is no display, so commands run as written on a headless machine."""

import os
import subprocess
import sys

import pytest

from robel_dm import gl_backend


def test_a_set_backend_or_a_display_is_left_alone():
  for environ in ({'MUJOCO_GL': 'osmesa'}, {'DISPLAY': ':0'},
                  {'WAYLAND_DISPLAY': 'wayland-0'}):  # fmt: skip
    before = dict(environ)
    assert gl_backend.choose(environ) is None
    assert environ == before


def test_without_a_display_an_offscreen_backend_is_chosen():
  environ = {}
  chosen = gl_backend.choose(environ)
  assert chosen in ('egl', 'osmesa')  # This machine has Mesa's EGL.
  assert environ == {'MUJOCO_GL': chosen}


def _headless():
  return {
    k: v for k, v in os.environ.items()
    if k not in ('MUJOCO_GL', 'DISPLAY', 'WAYLAND_DISPLAY',
                 'PYOPENGL_PLATFORM')
  }  # fmt: skip


@pytest.mark.slow
def test_a_command_needs_no_environment_variable(tmp_path):
  # Before: GLFW's 'The DISPLAY environment variable is missing' warning.
  result = subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.evaluate', '--episodes=1'],
    capture_output=True, text=True, env=_headless(), cwd=tmp_path, timeout=300,
  )  # fmt: skip
  assert result.returncode == 0, result.stderr
  assert 'GLFW' not in result.stderr and 'DISPLAY' not in result.stderr
  shown = subprocess.run(
    [sys.executable, '-c',
     'import os, robel_dm; from robel_dm import gl_backend; '
     'print(os.environ["MUJOCO_GL"], gl_backend.describe())'],
    capture_output=True, text=True, env=_headless(), timeout=60,
  )  # fmt: skip
  assert 'robel_dm chose it' in shown.stdout


@pytest.mark.slow
def test_the_viewer_undoes_the_offscreen_choice(tmp_path):
  # It needs a window: with no display it says so, not 'MUJOCO_GL=egl'.
  result = subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.view', '--task=pose_fixed'],
    capture_output=True, text=True, env=_headless(), cwd=tmp_path, timeout=120,
  )  # fmt: skip
  assert result.returncode == 2
  assert result.stderr.strip().splitlines()[-1].startswith('error: no display')
