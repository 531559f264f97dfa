"""Picks MuJoCo's offscreen OpenGL backend when nothing else did.

dm_control reads MUJOCO_GL once, when it is first imported; unset, it uses
GLFW, which needs a display and otherwise prints an X11 warning and cannot
render. Where MUJOCO_GL is unset and there is no display, importing
robel_dm (which imports this module first) sets MUJOCO_GL to the offscreen
backend this machine has (EGL, else OSMesa), so videos and tests work
without setting anything. `CHOSEN` says what was picked (None: nothing).
The viewer, which needs a window, undoes an automatic pick (see
robel_dm.commands.view).
"""

import ctypes
import os
import sys

# The libraries dm_control's backends load, in order of preference.
_OFFSCREEN_LIBRARIES = (('egl', 'libEGL.so.1'), ('osmesa', 'libOSMesa.so.8'),
                        ('osmesa', 'libOSMesa.so'))  # fmt: skip


def choose(environ=os.environ) -> str | None:
  """Sets MUJOCO_GL in `environ` to a working offscreen backend if it is
  unset and there is no display; returns the backend set, or None."""
  if environ.get('MUJOCO_GL') or environ.get('DISPLAY'):
    return None
  if environ.get('WAYLAND_DISPLAY') or sys.platform != 'linux':
    return None
  for backend, library in _OFFSCREEN_LIBRARIES:
    try:
      ctypes.CDLL(library)
    except OSError:
      continue
    environ['MUJOCO_GL'] = backend
    return backend
  return None


def describe() -> str:
  """MUJOCO_GL's value, and whether robel_dm chose it."""
  backend = os.environ.get('MUJOCO_GL', 'glfw (unset)')
  if CHOSEN:
    return f'MUJOCO_GL={backend} (robel_dm chose it: unset, no display)'
  return f'MUJOCO_GL={backend}'


CHOSEN = choose()
