"""The repository stands on its own: every document it cites is in it."""

import pathlib
import re
import subprocess

import pytest

_ROOT = pathlib.Path(__file__).resolve().parent.parent
_SKIPPED_DIRS = {'.git', '.venv', 'venv', 'build', 'dist', '__pycache__'}
_TEXT_SUFFIXES = {'.py', '.md', '.xml', '.json', '.toml', '.txt', '.cfg', ''}

# A cited document: a name ending in .md, optionally with a path.
_MD_REFERENCE = re.compile(r'(?<![\w/.-])([\w./-]*[\w-]+\.md)\b')
# Markdown links to files in the repository: [text](path) with no scheme.
_MD_LINK = re.compile(r'\]\((?![a-z]+:|#)([^)#\s]+)')
# Documents that once were cited but live outside the repository.
_OUTSIDE = re.compile(
  r'robel_facts|composer_guide|robel_paper|shared/reference'
)


def _tracked_files() -> list[pathlib.Path]:
  """Files in version control (the tree minus build outputs without git)."""
  try:
    listing = subprocess.run(
      ['git', 'ls-files', '-z'],
      cwd=_ROOT,
      capture_output=True,
      check=True,
      text=True,
    ).stdout
    names = [name for name in listing.split('\0') if name]
  except (OSError, subprocess.CalledProcessError):
    names = [
      str(path.relative_to(_ROOT))
      for path in _ROOT.rglob('*')
      if path.is_file() and not _SKIPPED_DIRS & set(path.parts)
    ]
  return [_ROOT / name for name in names]


def _text_files():
  for path in _tracked_files():
    if path.suffix in _TEXT_SUFFIXES and path.is_file():
      try:
        yield path, path.read_text(encoding='utf-8')
      except UnicodeDecodeError:
        continue


def _resolves(citing: pathlib.Path, reference: str) -> bool:
  """Whether `reference` is a path to a file (or folder) of the repository,
  relative to the citing file or to the repository's root."""
  reference = reference.rstrip('.,:;')
  return any((base / reference).exists() for base in (citing.parent, _ROOT))


def test_every_cited_document_is_in_the_repository():
  files = list(_text_files())
  assert files, 'found no files to check'
  unresolved = []
  for path, text in files:
    if path.resolve() == pathlib.Path(__file__).resolve():
      continue  # This file names the outside documents it forbids.
    relative = path.relative_to(_ROOT)
    for number, line in enumerate(text.splitlines(), 1):
      if _OUTSIDE.search(line):
        unresolved.append(f'{relative}:{number}: {line.strip()}')
        continue
      references = _MD_REFERENCE.findall(line)
      if path.suffix == '.md':
        references += _MD_LINK.findall(line)
      for reference in references:
        if not _resolves(path, reference):
          unresolved.append(f'{relative}:{number}: {reference}')
  assert not unresolved, 'citations of documents not in the repository:\n' + (
    '\n'.join(unresolved)
  )


@pytest.mark.parametrize(
  'line',
  [
    'see robel_facts 2.6',
    'dynamixel.md section 1.1',
    'details in [the guide](docs/missing.md)',
  ],
)
def test_the_check_catches_outside_citations(line, tmp_path):
  # The checker itself: each line cites something absent from this tree.
  citing = tmp_path / 'module.py'
  outside = bool(_OUTSIDE.search(line))
  references = _MD_REFERENCE.findall(line) + _MD_LINK.findall(line)
  assert outside or not all(
    _resolves(citing, reference) for reference in references
  )
