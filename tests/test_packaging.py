"""The models reach an installed wheel, and an installed robel_dm finds them."""

import os
import pathlib
import shutil
import subprocess
import sys
import tarfile
import zipfile

import pytest

_REPO = pathlib.Path(__file__).resolve().parents[1]
_MODELS = sorted(
  path.relative_to(_REPO / 'xml').as_posix()
  for path in (_REPO / 'xml').rglob('*.xml')
)


def _needs_build_tools():
  # Builds run without isolation, on the dev extra's build and hatchling.
  pytest.importorskip('build', reason='needs robel_dm[dev]')
  pytest.importorskip('hatchling', reason='needs robel_dm[dev]')


@pytest.fixture(scope='module')
def wheel(tmp_path_factory) -> pathlib.Path:
  _needs_build_tools()
  # Build from a copy so that no build artifacts land in the checkout.
  source = tmp_path_factory.mktemp('source')
  for name in ('pyproject.toml', 'README.md'):
    shutil.copy(_REPO / name, source / name)
  for name in ('robel_dm', 'xml', 'policies'):
    shutil.copytree(
      _REPO / name, source / name, ignore=shutil.ignore_patterns('__pycache__')
    )
  out = tmp_path_factory.mktemp('dist')
  # No isolation: the build backend comes from the dev extra (no network).
  subprocess.run(
    [sys.executable, '-m', 'build', '--wheel', '--no-isolation',
     '--outdir', str(out), str(source)],
    check=True, capture_output=True,
  )  # fmt: skip
  (wheel_path,) = out.glob('robel_dm-*.whl')
  return wheel_path


def test_wheel_contains_every_model(wheel):
  names = set(zipfile.ZipFile(wheel).namelist())
  missing = [m for m in _MODELS if f'robel_dm/xml/{m}' not in names]
  assert _MODELS and not missing
  shipped = [
    f'robel_dm/baseline_policies/{path.name}'
    for path in (_REPO / 'policies').iterdir()
  ]
  assert shipped and set(shipped) <= names


@pytest.mark.slow
def test_installed_wheel_loads_tasks_from_packaged_models(wheel, tmp_path):
  target = tmp_path / 'site'
  subprocess.run(
    [sys.executable, '-m', 'pip', 'install', '--no-deps', '--no-index',
     '--target', str(target), str(wheel)],
    check=True, capture_output=True,
  )  # fmt: skip
  script = (
    'import pathlib, robel_dm\n'
    'from robel_dm import assets, suite\n'
    'assert pathlib.Path(robel_dm.__file__).is_relative_to(pathlib.Path('
    f'{str(target)!r})), robel_dm.__file__\n'
    'print(assets.baselines_dir())\n'
    'print(assets.xml_dir())\n'
    "env = suite.load('dclaw', 'turn_fixed', task_kwargs={'valve': 'valve4'})\n"
    'env.reset()\n'
  )
  # Run outside the checkout so that only the installed copy is importable.
  env = dict(os.environ, PYTHONPATH=str(target), MUJOCO_GL='egl')
  result = subprocess.run(
    [sys.executable, '-c', script],
    cwd=tmp_path, env=env, check=True, capture_output=True, text=True,
  )  # fmt: skip
  *_, baselines_dir, xml_dir = result.stdout.strip().splitlines()
  assert pathlib.Path(xml_dir) == target / 'robel_dm' / 'xml'
  assert pathlib.Path(baselines_dir) == (
    target / 'robel_dm' / 'baseline_policies'
  )


@pytest.mark.slow
def test_source_distribution_is_the_repository_less_ci(tmp_path):
  # The tests read docs/ (the baseline table) and benchmarks/: an sdist
  # missing a tracked file could not run its own tests.
  _needs_build_tools()
  try:
    listing = subprocess.run(
      ['git', 'ls-files', '-z'],
      cwd=_REPO, capture_output=True, check=True, text=True,
    ).stdout  # fmt: skip
  except (OSError, subprocess.CalledProcessError):
    pytest.skip('needs a git checkout to know the tracked files')
  tracked = {name for name in listing.split('\0') if name}
  # Build from a copy of the tracked files: the checkout's untracked files
  # (runs/, caches) are not the question here.
  source = tmp_path / 'source'
  for name in tracked:
    (source / name).parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(_REPO / name, source / name)
  subprocess.run(
    [sys.executable, '-m', 'build', '--sdist', '--no-isolation',
     '--outdir', str(tmp_path / 'dist'), str(source)],
    check=True, capture_output=True,
  )  # fmt: skip
  (sdist,) = (tmp_path / 'dist').glob('robel_dm-*.tar.gz')
  with tarfile.open(sdist) as archive:
    names = {
      name.split('/', 1)[1] for name in archive.getnames() if '/' in name
    }
  expected = {name for name in tracked if not name.startswith('.ci/')}
  assert expected - names == set()
  assert names - expected == {'PKG-INFO'}
