"""Architecture rules, checked by tools rather than by hope.

* The import contracts of `pyproject.toml` ([tool.importlinter]) hold:
  commands on top and independent, every module imports only its layer and
  the layers below, the simulation core never imports the hardware (nor the
  hardware a task) nor an optional extra, no package has an import cycle,
  and no import is waived.
* Only `robel_dm/environment.py` touches dm_control's private names.
* No function of the package or of the benchmarks is 80 lines or longer.
"""

import ast
import pathlib
import re
import shutil
import subprocess
import sys

import pytest
import tomllib

_ROOT = pathlib.Path(__file__).resolve().parent.parent
_PACKAGE = _ROOT / 'robel_dm'
_MAX_FUNCTION_LINES = 80

# Private names of dm_control's composer.Environment and observation
# Updater that robel_dm relies on (see robel_dm/environment.py); generic
# ones such as `_task` or `_physics` are robel_dm's own names elsewhere.
_DM_CONTROL_PRIVATE = (
  '_step_counter',
  '_enabled_list',
  '_enabled_structure',
  '_is_nested',
  '_strip_singleton_buffer_dim',
  '_physics_steps_per_control_step',
  '_hooks',
  '_physics_proxy',
  '_mjcf_never_compiled',
  '_recompile_mjcf_every_episode',
  '_reset_next_step',
  '_n_sub_steps',
  '_raise_exception_on_physics_error',
  '_observation_updater',
  '_recompile_physics',
  '_make_observation_updater',
  '_legacy_step',
  '_delayed_observation_padding',
  '_strip_singleton_obs_buffer_dim',
)
_ADAPTER = _PACKAGE / 'environment.py'


def _lint_imports(python_path: pathlib.Path | None = None):
  executable = shutil.which(
    'lint-imports', path=str(pathlib.Path(sys.executable).parent)
  )
  if executable is None:
    pytest.skip('lint-imports missing: needs robel_dm[dev]')
  env = None
  if python_path is not None:
    env = {'PYTHONPATH': str(python_path), 'PATH': '/usr/bin:/bin'}
  return subprocess.run(
    [executable, '--config', str(_ROOT / 'pyproject.toml'), '--no-cache'],
    cwd=python_path or _ROOT,  # lint-imports looks in its directory first.
    capture_output=True,
    text=True,
    env=env,
    check=False,
  )


@pytest.mark.slow
def test_import_layers_hold():
  result = _lint_imports()
  assert result.returncode == 0, result.stdout + result.stderr
  assert '0 broken' in result.stdout


@pytest.mark.slow
@pytest.mark.parametrize(
  'module, imported, broken',
  [
    # A task reaching into the hardware beneath it.
    ('tasks/base.py', 'robel_dm.hardware.physics', 'robel_dm.tasks.base'),
    # The hardware depending on a task.
    ('hardware/physics.py', 'robel_dm.tasks.base', 'robel_dm.hardware.physics'),
    # The suite reaching up into a library.
    (
      'suite.py',
      'robel_dm.learning.agents',
      'robel_dm.suite -> robel_dm.learning',
    ),
    # A library importing a command.
    (
      'policies.py',
      'robel_dm.commands.evaluate',
      'robel_dm.policies -> robel_dm.commands',
    ),
    # One command importing another.
    (
      'commands/plot.py',
      'robel_dm.commands.view',
      'robel_dm.commands.plot -> robel_dm.commands.view',
    ),
    # The simulation core importing an optional extra.
    ('tasks/base.py', 'torch', 'robel_dm.tasks.base -> torch'),
    # A cycle between two libraries of one layer (learning imports policies).
    (
      'policies.py',
      'robel_dm.learning.agents',
      '.policies -> .learning',
    ),
    # A cycle inside the hardware package (environment imports physics).
    (
      'hardware/physics.py',
      'robel_dm.hardware.environment',
      '.physics -> .environment',
    ),
  ],
)
def test_the_contracts_catch_a_bad_import(tmp_path, module, imported, broken):
  # A copy of the package with one bad import added: a contract must break.
  shutil.copytree(
    _PACKAGE, tmp_path / 'robel_dm', ignore=shutil.ignore_patterns('*.pyc')
  )
  path = tmp_path / 'robel_dm' / module
  path.write_text(path.read_text() + f'\nimport {imported}  # noqa\n')
  result = _lint_imports(python_path=tmp_path)
  assert result.returncode != 0, result.stdout
  assert broken in result.stdout


def _contracts() -> list[dict]:
  with open(_ROOT / 'pyproject.toml', 'rb') as file:
    return tomllib.load(file)['tool']['importlinter']['contracts']


def _top_level_modules() -> set[str]:
  return {
    f'robel_dm.{path.stem}'
    for path in _PACKAGE.iterdir()
    if (path.suffix == '.py' and path.stem != '__init__')
    or (path / '__init__.py').is_file()
  }


def test_no_contract_is_weakened():
  contracts = _contracts()
  assert not [c['name'] for c in contracts if 'ignore_imports' in c]
  (layers,) = [c for c in contracts if c['type'] == 'layers']
  # Every module in one layer; the commands on top, independent.
  placed = [
    module.strip()
    for layer in layers['layers']
    for module in layer.replace(':', '|').split('|')
  ]
  assert sorted(placed) == sorted(_top_level_modules())
  assert layers['layers'][0] == 'robel_dm.commands'
  # The commands are independent of each other.
  (independence,) = [c for c in contracts if c['type'] == 'independence']
  assert independence['modules'] == ['robel_dm.commands.*']
  assert layers.get('exhaustive', False) is False  # Checked above instead.
  # Modules of a lower layer may import each other only because no cycle
  # can hide among them: the acyclic contract covers every package.
  (acyclic,) = [c for c in contracts if c['type'] == 'acyclic_siblings']
  assert set(acyclic['ancestors']) == {
    'robel_dm',
    'robel_dm.hardware',
    'robel_dm.evaluation',
  }
  assert 'depth' not in acyclic and 'skip_descendants' not in acyclic
  forbidden = {c['name']: c for c in contracts if c['type'] == 'forbidden'}
  assert (
    'robel_dm.hardware'
    in (
      forbidden['The simulation core never imports the hardware'][
        'forbidden_modules'
      ]
    )
  )
  assert (
    'robel_dm.tasks'
    in (forbidden['The hardware never imports a task']['forbidden_modules'])
  )


def _foreign_private_reads(path: pathlib.Path) -> list[str]:
  """Every `x._name` in `path` where x is not the object itself (`self`,
  `cls`, or `super()`: the object's own method as its parent class has
  it): a private name read from another object (dunder names aside)."""
  found = []
  for node in ast.walk(ast.parse(path.read_text())):
    if (
      isinstance(node, ast.Attribute)
      and node.attr.startswith('_')
      and not node.attr.startswith('__')
      and not _own(node.value)
    ):
      found.append(f'line {node.lineno}: {ast.unparse(node)}')
  return found


def _own(node: ast.expr) -> bool:
  if isinstance(node, ast.Name):
    return node.id in ('self', 'cls')
  return (
    isinstance(node, ast.Call)
    and isinstance(node.func, ast.Name)
    and node.func.id == 'super'
    and not node.args
  )


@pytest.mark.parametrize(
  'module',
  sorted(p for p in _PACKAGE.rglob('*.py') if p != _ADAPTER),
  ids=lambda p: str(p.relative_to(_ROOT)),
)
def test_only_the_adapter_reads_other_objects_private_names(module):
  # A rule, not a list: outside the dm_control adapter no code reads a
  # private name of another object (a dm_control or MuJoCo one above all).
  found = _foreign_private_reads(module)
  assert not found, f'{module.name} reads private names: {found}'


def test_the_private_name_rule_catches_a_physics_internal(tmp_path):
  probe = tmp_path / 'probe.py'
  probe.write_text('def f(physics):\n  return physics._contexts\n')
  assert _foreign_private_reads(probe) == ['line 2: physics._contexts']
  # An override calling its parent's version reads its own name; a
  # two-argument super() of another object does not.
  probe.write_text(
    'class A(B):\n  def _setup(self, other):\n    super()._setup()\n'
    '    super(B, other)._setup()\n'
  )
  assert _foreign_private_reads(probe) == ['line 4: super(B, other)._setup']


def test_the_adapter_documents_every_private_name_it_uses():
  text = _ADAPTER.read_text()
  docstring = text.split('"""')[1]
  code = text.split('"""', 2)[2]
  used = {
    name
    for name in _DM_CONTROL_PRIVATE
    if re.search(rf'\.{name}\b|def {name}\b', code)
  }
  assert used, 'the adapter no longer uses private names: update this test'
  assert not [name for name in used if name not in docstring]


def _long_functions(path: pathlib.Path, limit: int) -> list[str]:
  """The functions (and methods) of a module of `limit` lines or more."""
  tree = ast.parse(path.read_text())
  return [
    f'{node.name} (line {node.lineno}): {node.end_lineno - node.lineno + 1}'
    for node in ast.walk(tree)
    if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
    and node.end_lineno - node.lineno + 1 >= limit
  ]


@pytest.mark.parametrize(
  'module',
  # The package's and the benchmarks' modules: split by concept, with
  # short functions (a module is as long as its concept needs).
  sorted([*_PACKAGE.rglob('*.py'), *(_ROOT / 'benchmarks').glob('*.py')]),
  ids=lambda p: str(p.relative_to(_ROOT)),
)
def test_functions_stay_short(module):
  long = _long_functions(module, _MAX_FUNCTION_LINES)
  assert not long, f'{module.name}: functions of 80 lines or more: {long}'


def test_the_function_rule_catches_a_long_function(tmp_path):
  probe = tmp_path / 'probe.py'
  body = ''.join(f'  x{i} = {i}\n' for i in range(_MAX_FUNCTION_LINES))
  probe.write_text(f'def short():\n  pass\n\n\ndef long():\n{body}')
  assert _long_functions(probe, _MAX_FUNCTION_LINES) == [
    f'long (line 5): {_MAX_FUNCTION_LINES + 1}'
  ]


def test_hardware_options_and_connection_are_typed():
  # One typed value travels down; no field is typed `object` or untyped.
  for path in ('hardware/options.py', 'hardware/connection.py'):
    tree = ast.parse((_PACKAGE / path).read_text())
    classes = [n for n in tree.body if isinstance(n, ast.ClassDef)]
    fields = [
      node
      for cls in classes
      for node in cls.body
      if isinstance(node, ast.AnnAssign)
    ]
    assert fields, path
    untyped = [
      ast.unparse(f.target)
      for f in fields
      if ast.unparse(f.annotation) == 'object'
    ]
    assert not untyped, f'{path}: {untyped}'


def _ruff() -> str:
  executable = shutil.which(
    'ruff', path=str(pathlib.Path(sys.executable).parent)
  )
  if executable is None:
    pytest.skip('ruff missing: needs robel_dm[dev]')
  return executable


def test_ruff_finds_nothing():
  # Style, imports, and the function limits: parameters, statements and
  # complexity (pyproject.toml's [tool.ruff.lint]).
  result = subprocess.run(
    [_ruff(), 'check', '--no-cache', 'robel_dm', 'tests', 'benchmarks'],
    cwd=_ROOT,
    capture_output=True,
    text=True,
    check=False,
  )
  assert result.returncode == 0, result.stdout + result.stderr


def test_ruff_keeps_the_function_limits(tmp_path):
  with open(_ROOT / 'pyproject.toml', 'rb') as file:
    lint = tomllib.load(file)['tool']['ruff']['lint']
  assert {'PLR0913', 'PLR0915', 'C901'} <= set(lint['select'])
  assert lint['pylint']['max-args'] <= 8
  assert lint['mccabe']['max-complexity'] <= 12
  # A function of nine parameters is caught.
  probe = tmp_path / 'probe.py'
  probe.write_text('def f(a, b, c, d, e, f, g, h, i):\n  return a\n')
  result = subprocess.run(
    [_ruff(), 'check', '--no-cache', '--config', str(_ROOT / 'pyproject.toml'),
     str(probe)],
    capture_output=True, text=True, check=False,
  )  # fmt: skip
  assert 'PLR0913' in result.stdout
