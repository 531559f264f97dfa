"""Control-step and reset speed of every task against raw MuJoCo.

For each task this measures, in one process and interleaved round by round:
  * `env.step` per control step, driven by a fixed sequence of random actions;
  * the raw ceiling: `mujoco.mj_step(model, data, nstep)` on the same compiled
    model, with `nstep` = physics steps per control step, replaying from the
    same initial state the joint targets the environment sent, so both runs
    simulate the same trajectory (no Python around it but the loop);
  * `env.reset`, and for tasks whose reset lets the robot settle (D'Kitty
    Stand) also a reset without settling (`settle_substeps=0`): the
    difference is the settling.
Each figure is the minimum over rounds of the per-round mean (other jobs on a
shared machine only ever add time). Prints a table; `--json` also writes it.

    MUJOCO_GL=egl python benchmarks/bench_step.py [--steps 200] [--rounds 7]
"""

import argparse
import json
import time

import mujoco
import numpy as np

from robel_dm import suite
from robel_dm.entities import dkitty


def _time_env_steps(env, actions, controls) -> tuple[float, int]:
  """Times env.step over `actions`; logs the joint targets it sent.

  Returns:
    Seconds per step, and how many steps ended an episode (a fall): those
    runs include a reset and do not replay, so they are not comparable.
  """
  step = env.step
  ctrl = env.physics.data.ctrl
  ends = 0
  start = time.perf_counter()
  for i, action in enumerate(actions):
    ends += step(action).last()
    controls[i] = ctrl
  return (time.perf_counter() - start) / len(actions), ends


def _time_raw_steps(model, data, initial_data, controls, nstep) -> float:
  mujoco.mj_copyData(data, model, initial_data)
  mj_step = mujoco.mj_step
  ctrl = data.ctrl
  start = time.perf_counter()
  for control in controls:
    ctrl[:] = control
    mj_step(model, data, nstep)
  return (time.perf_counter() - start) / len(controls)


def _time_resets(env, count) -> float:
  start = time.perf_counter()
  for _ in range(count):
    env.reset()
  return (time.perf_counter() - start) / count


# Actions: uniform in [-1, 1] around a centre pose, scaled. The D'Kitty gets
# small ones around standing, or it falls, ending the episode mid-run.
_ACTION_CENTRE_POSE = {'dclaw': None, 'dkitty': dkitty.STANDING_POSE}
_ACTION_SCALE = {'dclaw': 1.0, 'dkitty': 0.15}


def _actions(env, domain, steps):
  rng = np.random.default_rng(0)
  shape = (steps,) + env.action_spec().shape
  pose = _ACTION_CENTRE_POSE[domain]
  centre = 0.0 if pose is None else env.task.normalize_joint_targets(pose)
  return np.clip(
    centre + _ACTION_SCALE[domain] * rng.uniform(-1.0, 1.0, shape), -1, 1
  )


def bench_task(domain, task, steps, rounds, resets):
  # No time limit: the timed stretch is uninterrupted control steps.
  env = suite.load(domain, task, seed=0, time_limit=float('inf'))
  env.reset()
  physics = env.physics
  model = physics.model.ptr
  data = mujoco.MjData(model)
  initial_data = mujoco.MjData(model)
  nstep = env.task.physics_steps_per_control_step
  actions = _actions(env, domain, steps)
  controls = np.zeros((steps, model.nu))
  # The same task without settling, for its reset time alone.
  unsettled = env
  if env.task.settle_substeps:
    unsettled = suite.load(
      domain, task, seed=0, task_kwargs={'settle_substeps': 0}
    )
  env_times, raw_times, reset_times, bare_reset_times = [], [], [], []
  falls = 0
  for _ in range(rounds):
    bare_reset_times.append(_time_resets(unsettled, resets))
    reset_times.append(_time_resets(env, resets))
    mujoco.mj_copyData(initial_data, model, physics.data.ptr)
    env_time, ends = _time_env_steps(env, actions, controls)
    if ends:
      falls += 1
      continue
    env_times.append(env_time)
    raw_times.append(
      _time_raw_steps(model, data, initial_data, controls, nstep)
    )
  if not env_times:
    raise RuntimeError(f'{domain}/{task}: every run ended early (fell)')
  env_step, raw_step = min(env_times), min(raw_times)
  reset = min(reset_times)
  bare_reset = min(bare_reset_times) if unsettled is not env else reset
  return {
    'domain': domain,
    'task': task,
    'substeps': nstep,
    'env_step_us': env_step * 1e6,
    'raw_step_us': raw_step * 1e6,
    'ratio': raw_step / env_step,
    'reset_ms': reset * 1e3,
    'settle_ms': (reset - bare_reset) * 1e3,
    'reset_without_settling_ms': bare_reset * 1e3,
    'rounds_discarded': falls,
  }


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--steps', type=int, default=200)
  parser.add_argument('--rounds', type=int, default=7)
  parser.add_argument('--resets', type=int, default=20)
  parser.add_argument('--domain', default=None)
  parser.add_argument('--task', default=None, help='only tasks containing this')
  parser.add_argument('--json', default=None, help='write results here')
  args = parser.parse_args()
  rows = []
  header = (
    f'{"task":<30} {"sub":>3} {"env.step us":>11} {"raw us":>8} '
    f'{"raw/env":>7} {"reset ms":>8} {"settle ms":>9} {"reset-settle":>12}'
  )
  print(header)
  print('-' * len(header))
  for domain, task in suite.ALL_TASKS:
    if args.domain and domain != args.domain:
      continue
    if args.task and args.task not in task:
      continue
    row = bench_task(domain, task, args.steps, args.rounds, args.resets)
    rows.append(row)
    print(
      f'{domain + "/" + task:<30} {row["substeps"]:>3} '
      f'{row["env_step_us"]:>11.1f} {row["raw_step_us"]:>8.1f} '
      f'{row["ratio"]:>7.3f} {row["reset_ms"]:>8.3f} '
      f'{row["settle_ms"]:>9.3f} {row["reset_without_settling_ms"]:>12.3f}',
      flush=True,
    )
  if args.json:
    with open(args.json, 'w') as f:
      json.dump(rows, f, indent=2)


if __name__ == '__main__':
  main()
