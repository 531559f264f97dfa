"""Episodes as MP4 videos, rendered offscreen from a named camera.

Rendering needs an OpenGL backend: `MUJOCO_GL=egl` on a headless machine
with a GPU driver or Mesa's EGL, `MUJOCO_GL=osmesa` where EGL is missing
(slower, software), `glfw` under a display. Videos are H.264 MP4 written by
imageio-ffmpeg's bundled ffmpeg (the `video` extra). Goal markers (the
valve's target, the D'Kitty's targets) are part of the scene, so they show.
"""

from collections.abc import Callable
import pathlib

import dm_env
import numpy as np

from robel_dm import constants

# Frame size, pixels (H.264 wants even sizes).
DEFAULT_HEIGHT = 480
DEFAULT_WIDTH = 640


class VideoError(RuntimeError):
  """Rendering or encoding failed (no GL backend, no ffmpeg, bad camera)."""


def camera_names(env: dm_env.Environment) -> list[str]:
  model = env.physics.model
  return [model.id2name(i, 'camera') for i in range(model.ncam)]


def resolve_camera(env: dm_env.Environment, camera: str) -> str:
  """The model's name of `camera`: as given, or the one camera whose name
  ends in it (`tracking_top` for `dkitty/tracking_top`, as xml/README.md
  names them).

  Raises:
    VideoError: naming the cameras if `camera` is none of them (or ends
      more than one).
  """
  names = camera_names(env)
  if camera in names:
    return camera
  matches = [name for name in names if name.split('/')[-1] == camera]
  if len(matches) != 1:
    raise VideoError(f'no camera {camera!r}; this task has {names}')
  return matches[0]


def check_camera(env: dm_env.Environment, camera: str) -> None:
  """Raises `VideoError` naming the cameras if `camera` is not one."""
  resolve_camera(env, camera)


class VideoWriter:
  """Writes the frames of one episode to an MP4 file as they come."""

  def __init__(
    self,
    path: str | pathlib.Path,
    fps: float,
    size: tuple[int, int] = (DEFAULT_HEIGHT, DEFAULT_WIDTH),
  ):
    try:
      import imageio_ffmpeg  # noqa: PLC0415 (the video extra)
    except ImportError as error:
      raise VideoError(
        'videos need imageio-ffmpeg: ' + constants.INSTALL_EXTRA.format('video')
      ) from error
    self.path = pathlib.Path(path)
    self.frames = 0
    self._open = lambda: imageio_ffmpeg.write_frames(
      str(self.path),
      (size[1], size[0]),
      fps=fps,
      codec='libx264',
      pix_fmt_out='yuv420p',
      macro_block_size=2,
      ffmpeg_log_level='error',
    )
    # ffmpeg starts with the first frame: a render that fails before it
    # leaves no file behind.
    self._writer = None

  def add(self, frame: np.ndarray) -> None:
    if self._writer is None:
      self._writer = self._open()
      self._writer.send(None)  # Starts ffmpeg.
    self._writer.send(np.ascontiguousarray(frame, dtype=np.uint8))
    self.frames += 1

  def close(self) -> None:
    if self._writer is not None:
      self._writer.close()


def render(
  env: dm_env.Environment,
  camera: str,
  size: tuple[int, int] = (DEFAULT_HEIGHT, DEFAULT_WIDTH),
) -> np.ndarray:
  """One RGB frame of the current state.

  Raises:
    VideoError: if offscreen rendering is unavailable.
  """
  height, width = size
  camera_id = resolve_camera(env, camera)
  try:
    return env.physics.render(height=height, width=width, camera_id=camera_id)
  except Exception as error:  # dm_control raises several kinds here.
    raise VideoError(
      f'offscreen rendering failed ({error}); set MUJOCO_GL=egl (or osmesa '
      'where EGL is missing) before Python starts'
    ) from error


def record_episode(
  env: dm_env.Environment,
  policy: Callable[[dm_env.TimeStep], np.ndarray],
  path: str | pathlib.Path,
  camera: str,
  size: tuple[int, int] = (DEFAULT_HEIGHT, DEFAULT_WIDTH),
) -> tuple[dm_env.TimeStep, int]:
  """Runs one episode and writes it as a video, one frame per step.

  Returns:
    The last timestep and the number of frames written (steps + 1).
  """
  camera = resolve_camera(env, camera)
  writer = VideoWriter(path, fps=1 / env.control_timestep(), size=size)
  try:
    timestep = env.reset()
    writer.add(render(env, camera, size))
    while not timestep.last():
      timestep = env.step(policy(timestep))
      writer.add(render(env, camera, size))
  finally:
    writer.close()
  return timestep, writer.frames
