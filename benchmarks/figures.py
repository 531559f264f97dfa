r"""Renders the pictures in the docs: one frame of each camera of both robots.

    python benchmarks/figures.py [--output=docs/images] [--size=360x480]

For each documented camera (xml/README.md) it writes
`<domain>_<camera>.png`: the D'Claw on turn_fixed and the D'Kitty on
walk_fixed after a few control steps of the shipped baseline policy (the
robot in a typical pose, the goal marker in view). Rendering is offscreen
(robel_dm picks the backend when MUJOCO_GL is unset); in software a frame
takes about a second at this size.
"""

import argparse
import pathlib

import numpy as np

from robel_dm import policies, suite, video

# (domain, task, steps of the baseline policy before the picture, cameras).
SCENES = (
  ('dclaw', 'turn_fixed', 20, ('front', 'side', 'closeup')),
  (
    'dkitty',
    'walk_fixed',
    40,
    ('follow', 'overview', 'tracking_top', 'tracking_side'),
  ),
)


def stills(output: pathlib.Path, size: tuple[int, int]) -> list[pathlib.Path]:
  """Writes the frames; returns their paths."""
  from PIL import Image  # noqa: PLC0415 (matplotlib's dependency)

  output.mkdir(parents=True, exist_ok=True)
  written = []
  for domain, task, steps, cameras in SCENES:
    env = suite.load(domain, task, seed=0)
    policy = policies.make_policy('baseline', env, 0, domain, task)
    timestep = env.reset()
    for _ in range(steps):
      timestep = env.step(policy(timestep))
    for camera in cameras:
      frame = video.render(env, camera, size)
      path = output / f'{domain}_{camera}.png'
      Image.fromarray(np.asarray(frame)).save(path, optimize=True)
      written.append(path)
    env.close()
  return written


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--output', default='docs/images')
  parser.add_argument('--size', default='360x480', help='HEIGHTxWIDTH')
  args = parser.parse_args()
  height, width = (int(v) for v in args.size.split('x'))
  for path in stills(pathlib.Path(args.output), (height, width)):
    print(f'wrote {path} ({path.stat().st_size // 1024} kB)')


if __name__ == '__main__':
  main()
