"""Which tasks a command runs, and with what arguments.

The command-line tools name tasks as --domain/--task ('all' for a sweep)
with --task_kwargs; this module turns those into checked values, and says
which tasks of a sweep a built-in policy can run.
"""

import json
from typing import Any

from robel_dm import policies, suite


def parse_task_kwargs(text: str) -> dict[str, Any]:
  """Parses --task_kwargs: a JSON object or comma-separated key=value pairs.

  Values of key=value pairs are read as JSON where possible (numbers, true,
  null, lists), otherwise as strings.

  Raises:
    ValueError: if the text is neither form.
  """
  text = text.strip()
  if not text:
    return {}
  if text.startswith('{'):
    try:
      parsed = json.loads(text)
    except json.JSONDecodeError as error:
      raise ValueError(f'--task_kwargs is not valid JSON: {error}') from error
    if not isinstance(parsed, dict):
      raise ValueError('--task_kwargs JSON must be an object')
    return parsed
  kwargs = {}
  for pair in text.split(','):
    key, sep, value = pair.partition('=')
    if not sep or not key.strip():
      raise ValueError(f'--task_kwargs entry {pair!r} is not key=value')
    try:
      kwargs[key.strip()] = json.loads(value)
    except json.JSONDecodeError:
      kwargs[key.strip()] = value.strip()
  return kwargs


def unavailable(
  policy: str, domain: str, task: str, task_kwargs: dict[str, Any]
) -> str | None:
  """Why a built-in `policy` ('reference', 'baseline') cannot run on the
  task, or None if it can (and for every other policy)."""
  if policy == policies.BASELINE:
    try:
      policies.baseline_path(domain, task)
    except policies.PolicyError:
      return 'no shipped baseline policy'
  elif policy == 'reference':
    env = suite.load(domain, task, task_kwargs=task_kwargs)
    try:
      env.reset()
      env.task.reference_action(env.physics)
    except NotImplementedError:
      return 'no reference controller'
    finally:
      env.close()
  return None


def select_tasks(domain: str, task: str) -> list[tuple[str, str]]:
  """The (domain, task) pairs that --domain and --task name ('all' for
  every domain or every task of the domain(s)).

  Raises:
    ValueError: for unknown names (with the suite's suggestions).
  """
  domains = list(suite.TASKS_BY_DOMAIN) if domain == 'all' else [domain]
  selected = []
  for name in domains:
    if name not in suite.TASKS_BY_DOMAIN:
      suite.load(name, task)  # Raises, naming the known domains.
    tasks = suite.TASKS_BY_DOMAIN[name]
    if task == 'all':
      selected += [(name, t) for t in tasks]
    elif task in tasks or domain != 'all':
      selected.append((name, task))
  if not selected:
    raise ValueError(f'no domain has a task {task!r}')
  for name, task_name in selected:
    if task_name not in suite.TASKS_BY_DOMAIN[name]:
      suite.load(name, task_name)  # Raises with the suggestions.
  return selected
