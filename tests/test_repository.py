"""The repository stands on its own: every document it cites is in it."""

import ast
import pathlib
import re
import subprocess

import pytest
import tomllib

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


@pytest.mark.slow
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


# --- The quick tier: `pytest -m "not slow"` ----------------------------------

# Modules whose every test trains or fits (marked slow as a whole).
_SLOW_MODULES = {
  'test_sac.py',
  'test_sysid_uncertainty.py',
  'test_telemetry.py',
}
# Modules of long runs (training, evaluation, system identification, videos).
_HEAVY_MODULES = (
  'test_baselines.py',
  'test_evaluate.py',
  'test_learning.py',
  'test_robot_training.py',
  'test_sysid.py',
  'test_training.py',
  'test_video.py',
)


def _is_slow_mark(node: ast.expr) -> bool:
  return ast.unparse(node) == 'pytest.mark.slow'


def _slow_marks(path: pathlib.Path) -> tuple[bool, dict[str, bool]]:
  """Whether a test module is marked slow, and each of its tests (functions
  and classes) whether marked slow as a whole (from the source)."""
  tree = ast.parse(path.read_text(encoding='utf-8'))
  module_slow = any(
    isinstance(node, ast.Assign)
    and any(getattr(t, 'id', None) == 'pytestmark' for t in node.targets)
    and _is_slow_mark(node.value)
    for node in tree.body
  )
  tests = {
    node.name: any(_is_slow_mark(d) for d in node.decorator_list)
    for node in tree.body
    if isinstance(node, (ast.FunctionDef, ast.ClassDef))
    and node.name.lower().startswith('test')
  }
  return module_slow, tests


def test_the_quick_tier_leaves_out_slow_tests_of_every_module_only():
  options = tomllib.loads((_ROOT / 'pyproject.toml').read_text())['tool'][
    'pytest'
  ]['ini_options']
  assert any(m.startswith('slow:') for m in options['markers'])
  assert '--strict-markers' in options['addopts']  # A misspelt mark fails.
  marks = {
    path.name: _slow_marks(path)
    for path in sorted((_ROOT / 'tests').glob('test_*.py'))
  }
  for name in _HEAVY_MODULES:
    assert any(marks[name][1].values()), f'{name}: no test marked slow'
  for name, (module_slow, tests) in marks.items():
    assert tests, f'{name}: no tests found'
    if name in _SLOW_MODULES:
      assert module_slow, f'{name}: pytestmark = pytest.mark.slow expected'
    else:
      assert not module_slow and not all(tests.values()), (
        f'{name}: every test is slow; the quick tier runs none of it'
      )
