"""The evaluation command's results file: checked before, written atomically.

`check_output` refuses, before anything moves, a --output that is not the
path of a regular file (a directory, a symbolic link, a device, a fifo),
that cannot be written, or that is a file the run reads (the policy).
`write_json` replaces the file in one step, so a failed write (a full disk)
or an interruption leaves the previous complete file as it was.
"""

from collections.abc import Iterable
import contextlib
import json
import os
import secrets
import stat

# What is at --output, when it is not a regular file.
_KINDS = (
  (stat.S_ISDIR, 'a directory'),
  (stat.S_ISCHR, 'a device'),
  (stat.S_ISBLK, 'a device'),
  (stat.S_ISFIFO, 'a fifo'),
  (stat.S_ISSOCK, 'a socket'),
)


class OutputError(RuntimeError):
  """Writing the results failed after the run started (e.g. a full disk)."""


def check_output(
  path: str | None, inputs: Iterable[tuple[str, str | None]] = ()
) -> None:
  """Fails before the first episode if the results cannot be written.

  Args:
    path: the --output file (None or empty: no results file).
    inputs: (flag, path) of every file the run reads, e.g. ('--policy',
      'p.npz'); None paths are skipped.

  Raises:
    ValueError: in one line, if `path` is not a regular file's path (an
      existing directory, symbolic link, device, fifo or socket), is one of
      `inputs` (the results would replace it), or its folder is missing or
      not writable.
  """
  if not path:
    return
  if path.endswith((os.sep, '/')):
    raise ValueError(f'--output: {path} names a folder, not a file')
  if os.path.islink(path):
    raise ValueError(
      f'--output: {path} is a symbolic link; give the path of a regular file'
    )
  for flag, name in inputs:
    if name and _same_file(path, name):
      raise ValueError(
        f'--output: {path} is the file of {flag}={name}; the results would '
        'replace it: give another path'
      )
  if os.path.exists(path):
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
      kind = next(
        (kind for test, kind in _KINDS if test(mode)), 'not a regular file'
      )
      raise ValueError(
        f'--output: {path} is {kind}; give the path of a regular file'
      )
  directory = os.path.dirname(os.path.abspath(path))
  if not os.path.isdir(directory):
    raise ValueError(f'--output: no folder {directory}')
  if not os.access(directory, os.W_OK) or (
    os.path.exists(path) and not os.access(path, os.W_OK)
  ):
    raise ValueError(f'--output: cannot write {path}')


def _same_file(path: str, other: str) -> bool:
  """Whether two paths name one existing file (through links, or another
  spelling)."""
  try:
    return os.path.samefile(path, other)
  except (OSError, ValueError):  # Either is missing, or not a path.
    return False


def write_json(path: str, data) -> None:
  """Writes `data` atomically: a reader, a failed write or an interruption
  never leaves a half-written file (the previous one stays whole).

  The JSON goes to a new file beside `path` (created exclusively: never
  through a symbolic link), is flushed to disk, then renamed over `path`.

  Raises:
    OSError: if the write fails (the previous file is untouched).
  """
  text = json.dumps(data, indent=2)
  directory, name = os.path.split(os.path.abspath(path))
  temporary = os.path.join(directory, f'.{name}.{secrets.token_hex(4)}.partial')
  created = False
  try:
    with open(temporary, 'x') as file:  # Exclusive: never through a link.
      created = True
      file.write(text)
      file.flush()
      os.fsync(file.fileno())
    os.replace(temporary, path)
  except BaseException:
    if created:
      with contextlib.suppress(OSError):
        os.unlink(temporary)
    raise


def save(path: str, data, episodes_saved: int) -> None:
  """`write_json`, with a failure as one line of `OutputError`.

  Args:
    path: the --output file.
    data: the results so far.
    episodes_saved: how many episodes the file holds already (from the
      last successful save), for the message.

  Raises:
    OutputError: if the write fails; `path` keeps the last saved results.
  """
  try:
    write_json(path, data)
  except OSError as error:
    reason = os.strerror(error.errno) if error.errno else str(error)
    kept = (
      f'{path} keeps the {episodes_saved} episode(s) saved before'
      if episodes_saved
      else 'nothing was saved'
    )
    raise OutputError(
      f'--output: cannot write {path}: {reason}; {kept}'
    ) from error
