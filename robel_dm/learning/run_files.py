"""The files a training run writes into its folder, and the checks that
keep one run from overwriting another."""

from collections.abc import Sequence
import pathlib
import shutil

from robel_dm.learning import telemetry

CHECKPOINT = 'checkpoint.zip'
REPLAY_BUFFER = 'replay_buffer.pkl'
ENV_STATE = 'env_state.pkl'
RANDOM_STREAMS = 'random_streams.pkl'
POLICY = 'policy.npz'
BEST_POLICY = 'policy_best.npz'
EVAL_LOG = 'eval.jsonl'
CURVE = 'learning_curve.png'
CONFIG = 'config.json'
METADATA = 'metadata.json'
# Any of these shows that a directory holds a run.
RUN_MARKERS = (CONFIG, EVAL_LOG, CHECKPOINT, POLICY)
# What a run writes; --overwrite removes these (and the TensorBoard events).
RUN_FILES = (
  CHECKPOINT,
  REPLAY_BUFFER,
  ENV_STATE,
  RANDOM_STREAMS,
  POLICY,
  BEST_POLICY,
  EVAL_LOG,
  CURVE,
  CONFIG,
  METADATA,
)
EVENT_FILES = 'events.out.tfevents.*'


def init_checkpoint(init_from: str | pathlib.Path) -> pathlib.Path:
  """The saved model a run starts from (`--init_from`): `init_from`, or
  the checkpoint in the run folder it names."""
  path = pathlib.Path(init_from)
  return path / CHECKPOINT if path.is_dir() else path


def check_output_dir(
  output: str | pathlib.Path,
  resume: bool,
  overwrite: bool,
  markers: Sequence[str] = RUN_MARKERS,
) -> None:
  """Raises ValueError if `resume` and `overwrite` are both asked, or if
  neither is and `output` already holds a run (one of `markers` exists).

  An absent or empty directory, or one holding only other files, is fine.
  """
  if resume and overwrite:
    raise ValueError(
      '--resume continues a run and --overwrite starts it over: pass one '
      'of them'
    )
  if resume or overwrite:
    return
  output = pathlib.Path(output)
  held = [name for name in markers if (output / name).exists()]
  if held:
    raise ValueError(
      f'{output} already holds a run ({held[0]}): pass --resume to continue '
      'it or --overwrite to start over'
    )


def clear_output_dir(
  output: str | pathlib.Path, names: Sequence[str] = RUN_FILES
) -> None:
  """Removes a previous run's files from `output`: `names` (files or
  folders) and the TensorBoard event files; other files stay."""
  output = pathlib.Path(output)
  for name in names:
    path = output / name
    if path.is_dir() and not path.is_symlink():
      shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
      path.unlink()
  for path in (output / telemetry.TENSORBOARD_DIR).glob(EVENT_FILES):
    path.unlink()
