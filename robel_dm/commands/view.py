r"""Opens dm_control's interactive viewer on a robel_dm task.

    robel-view --domain=dclaw --task=pose_fixed \
        --policy=reference

The viewer draws into a window, so it needs a display and MuJoCo's `glfw`
OpenGL backend: this command selects `glfw` when MUJOCO_GL is unset, and
explains what to change when MUJOCO_GL asks for offscreen rendering (`egl`,
`osmesa`) or there is no display. The viewer opens paused: Space runs and
pauses, Backspace restarts the episode, the mouse wheel zooms; see
dm_control's viewer documentation for the rest.
"""

import os
import sys

# Before dm_control is imported: it picks its OpenGL backend on import. An
# offscreen PyOpenGL platform inherited from a parent process (dm_control
# sets one for egl and osmesa) would break the window's context.
from robel_dm import gl_backend  # noqa: E402 (imports no dm_control)

if gl_backend.CHOSEN:  # robel_dm's offscreen pick: a window needs glfw.
  os.environ['MUJOCO_GL'] = 'glfw'
os.environ.setdefault('MUJOCO_GL', 'glfw')
if os.environ['MUJOCO_GL'] == 'glfw':
  os.environ.pop('PYOPENGL_PLATFORM', None)

from absl import app, flags  # noqa: E402

from robel_dm import command_help, policies, suite  # noqa: E402
from robel_dm.evaluation import task_args  # noqa: E402

_OFFSCREEN_BACKENDS = ('egl', 'osmesa')


def check_display(environ=os.environ) -> None:
  """Raises ValueError explaining why no viewer window can open."""
  backend = environ.get('MUJOCO_GL', 'glfw')
  if backend in _OFFSCREEN_BACKENDS:
    raise ValueError(
      f'MUJOCO_GL={backend} renders offscreen only; the viewer needs a '
      'window: unset MUJOCO_GL (or set MUJOCO_GL=glfw) and run it on a '
      'display. For videos on a headless machine use '
      '`robel-evaluate --video=DIR`.'
    )
  if not environ.get('DISPLAY') and not environ.get('WAYLAND_DISPLAY'):
    raise ValueError(
      'no display (DISPLAY is unset): run the viewer on a desktop, over X '
      'forwarding (ssh -X), or under a virtual display (xvfb-run)'
    )


def _define_flags() -> None:
  flags.DEFINE_string('domain', 'dclaw', 'Task domain.')
  flags.DEFINE_string('task', 'turn_fixed', 'Task name in the domain.')
  flags.DEFINE_string(
    'policy',
    None,
    'Policy to run (as for robel-evaluate); none: the viewer waits for '
    'you to act on the scene.',
  )
  flags.DEFINE_string('task_kwargs', '', 'Task arguments (as for evaluate).')
  flags.DEFINE_integer('seed', 0, 'Seed of the environment.')


FLAGS = flags.FLAGS


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f'unexpected arguments: {argv[1:]}')
  try:
    check_display()
    task_kwargs = _with_policy_options(
      task_args.parse_task_kwargs(FLAGS.task_kwargs)
    )
    env = suite.load(
      FLAGS.domain, FLAGS.task, seed=FLAGS.seed, task_kwargs=task_kwargs
    )
    policy = None
    if FLAGS.policy:
      policy = policies.make_policy(
        FLAGS.policy, env, FLAGS.seed, FLAGS.domain, FLAGS.task, task_kwargs
      )
    from dm_control import viewer  # noqa: PLC0415 (needs a display)

    viewer.launch(env, policy=policy)
  except (ValueError, RuntimeError) as error:  # Recording errors too.
    print(f'error: {error}', file=sys.stderr)
    return 2
  return 0


def _with_policy_options(task_kwargs: dict) -> dict:
  """The task arguments with a policy file's action map (and privileged
  observation) where they name none, as `robel-evaluate` does (said)."""
  if not FLAGS.policy:
    return task_kwargs
  checked = policies.check_file(
    FLAGS.policy, FLAGS.domain, FLAGS.task, task_kwargs
  )
  if checked is None:
    return task_kwargs
  return checked.task_kwargs_for(task_kwargs, print, 'viewing')


def run() -> None:
  """The command (`robel-view`, or `python -m robel_dm.commands.view`)."""
  command_help.run_absl(_define_flags, main, __doc__, __name__)


if __name__ == '__main__':
  run()
