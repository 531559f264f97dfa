"""Episodes of an evaluation spread over local processes or a Ray cluster.

Each episode runs from a reset seeded `seed + i` in a worker that keeps its
environment and policy between episodes, so the records equal those of a
serial run (`EvalConfig(workers=...)`, `ray_address=...`).
"""

from collections.abc import Iterator
import concurrent.futures
import contextlib
import json
import multiprocessing
import os
from typing import Any

from robel_dm import constants, policies, suite
from robel_dm.evaluation import episodes

# Each worker process keeps its environments and policies between episodes.
_WORKER_CACHE: dict = {}


def worker_episode(
  domain: str,
  task: str,
  task_kwargs: dict[str, Any] | None,
  policy: str,
  episode_seed: int,
) -> tuple[dict[str, Any], int, float]:
  """One episode in a worker process: its (record, steps, seconds), as
  `episodes.run_episode` returns them."""
  key = (domain, task, json.dumps(task_kwargs or {}, sort_keys=True), policy)
  if key not in _WORKER_CACHE:
    env = suite.load(domain, task, seed=episode_seed, task_kwargs=task_kwargs)
    act = policies.make_policy(
      policy, env, episode_seed, domain, task, task_kwargs
    )
    _WORKER_CACHE[key] = (env, act)
  env, act = _WORKER_CACHE[key]
  if policy == 'random':
    act = policies.make_policy(policy, env, episode_seed)
  return episodes.run_episode(env, act, episode_seed)


def local_episodes(
  domain: str,
  task: str,
  task_kwargs: dict[str, Any] | None,
  policy: str,
  seed: int,
  count: int,
  workers: int,
) -> Iterator[tuple[dict[str, Any], int, float]]:
  """Yields the episodes' (record, steps, seconds), in episode order, from
  `workers` local processes; episode i is reset with `seed + i`."""
  context = multiprocessing.get_context('spawn')  # MuJoCo and GL: no fork.
  with concurrent.futures.ProcessPoolExecutor(workers, context) as pool:
    futures = [
      pool.submit(
        worker_episode, domain, task, task_kwargs, policy, seed + episode
      )
      for episode in range(count)
    ]
    try:
      for future in futures:
        yield future.result()
    except BaseException:
      for future in futures:
        future.cancel()
      raise


@contextlib.contextmanager
def ray_session(address: str) -> Iterator[Any]:
  """Ray, connected to `address` ('local' starts an instance here) for the
  block unless already connected; the `scale` extra.

  Raises:
    ValueError: if Ray is not installed.
  """
  try:
    import ray  # noqa: PLC0415
  except ImportError as error:
    raise ValueError(
      'ray_address needs Ray: ' + constants.INSTALL_EXTRA.format('scale')
    ) from error
  started = not ray.is_initialized()
  if started:
    ray.init(
      address=None if address == 'local' else address,
      include_dashboard=False,
      log_to_driver=False,
      runtime_env={
        'env_vars': {'MUJOCO_GL': os.environ.get('MUJOCO_GL', 'egl')}
      },
    )
  try:
    yield ray
  finally:
    if started:
      ray.shutdown()


def ray_episodes(
  domain: str,
  task: str,
  task_kwargs: dict[str, Any] | None,
  policy: str,
  seed: int,
  count: int,
  address: str,
) -> Iterator[tuple[dict[str, Any], int, float]]:
  """Yields the episodes' (record, steps, seconds) from Ray tasks, in
  episode order (Ray from the `scale` extra); `address` as `ray_session`
  takes it."""
  with ray_session(address) as ray:
    remote = ray.remote(worker_episode)
    refs = [
      remote.remote(domain, task, task_kwargs, policy, seed + episode)
      for episode in range(count)
    ]
    for ref in refs:
      yield ray.get(ref)
