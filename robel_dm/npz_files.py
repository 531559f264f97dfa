"""The arrays of an .npz file, or one line saying why not.

`read_arrays` checks the sizes that the arrays' npy headers declare before
it reads any array: a compressed archive of a few megabytes can declare (and
unpack to) gigabytes, which numpy would allocate before finding anything
wrong. A damaged archive raises `ArchiveError` naming what numpy or zipfile
found, never their traceback.
"""

import math
import pathlib
import zipfile
import zlib

import numpy as np


class ArchiveError(ValueError):
  """An .npz file that is empty, damaged, not an archive, or too large."""


# What a damaged archive can raise while numpy reads it.
_READ_ERRORS = (
  OSError,
  EOFError,
  ValueError,
  KeyError,
  NotImplementedError,
  RuntimeError,  # An encrypted member.
  zipfile.BadZipFile,
  zlib.error,
)


def _one_line(error: BaseException) -> str:
  """An error as one line: its type, then its message if it has one."""
  message = ' '.join(str(error).split())
  name = type(error).__name__
  return f'{name}: {message}' if message else name


def read_arrays(path: pathlib.Path, max_bytes: int) -> dict[str, np.ndarray]:
  """The arrays of an .npz file, if they hold at most `max_bytes` in all.

  Raises:
    ArchiveError: in one line (without the path), if the file is empty, not
      an archive, damaged, or its arrays declare more than `max_bytes`.
    OSError: if the file cannot be opened.
  """
  if path.stat().st_size == 0:
    raise ArchiveError('the file is empty')
  with open(path, 'rb') as file:
    if not zipfile.is_zipfile(file):
      raise ArchiveError('not an .npz archive (truncated or another format)')
  try:
    with np.load(path, allow_pickle=False) as data:
      _check_declared_sizes(data.zip, max_bytes)
      return {name: data[name] for name in data.files}
  except ArchiveError:  # A ValueError, said in one line already.
    raise
  except _READ_ERRORS as error:
    raise ArchiveError(f'unreadable ({_one_line(error)})') from error


def _check_declared_sizes(archive: zipfile.ZipFile, max_bytes: int) -> None:
  """Raises `ArchiveError` if the arrays' npy headers declare more than
  `max_bytes` in all; reads the headers only."""
  total = 0
  for info in archive.infolist():
    with archive.open(info) as member:
      version = np.lib.format.read_magic(member)
      read_header = np.lib.format.read_array_header_1_0
      if version != (1, 0):  # Larger headers; np.load refuses unknown ones.
        read_header = np.lib.format.read_array_header_2_0
      shape, _, dtype = read_header(member)
    size = math.prod(shape) * dtype.itemsize
    total += size
    if total > max_bytes:
      in_all = f', {total / 2**20:,.1f} MiB in all' if total > size else ''
      raise ArchiveError(
        f'array {info.filename.removesuffix(".npy")} declares '
        f'{size / 2**20:,.1f} MiB ({dtype}, shape {shape}){in_all}: more '
        f'than the {max_bytes / 2**20:,.0f} MiB allowed'
      )
