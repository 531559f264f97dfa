"""Soaks of the virtual bus on a busy machine: random faults, late replies.

In-process (`device_path='virtual'`, simulated time), for the D'Claw (Pose)
and the D'Kitty (Stand): steps with a random fault injected before each one
(a motor silent for its next 1-3 packets, corrupted replies, lost goal
writes, a motor gone or back; often none), the robot reset after a fault or
at an episode's end. Prints the step times, apart for the steps that went
through and those that faulted (a fault also releases the robot, which asks
the silent motors to confirm their torque off for 0.5 s, together), and how
many took 1 s or more.

Standalone (`python -m robel_dm.commands.virtual_bus --driver=sim`, its own
process, real time): a D'Claw client writes goals and reads the state at
20 Hz, as the README's robot training does. Prints how long the reads took,
how many took longer than the SDK's reply deadline (~34 ms; the client
waits for them, as the bus publishes on its pty that it is behind) and how
many failed.

Run it on a loaded machine (the load average is printed):

    MUJOCO_GL=egl python benchmarks/virtual_bus_soak.py [--steps 1000] \
      [--seconds 120]
"""

import argparse
import logging
import os
import time

import numpy as np

from robel_dm import suite
from robel_dm.hardware import config as config_lib
from robel_dm.hardware import virtual
from robel_dm.hardware.dynamixel import client as dynamixel

_TASKS = {'dclaw': 'pose_fixed', 'dkitty': 'stand_fixed'}
_SDK_DEADLINE_S = 0.034
_RATE_HZ = 20


def _inject_random_fault(bus, rng) -> None:
  motor_id = int(rng.choice([servo.motor_id for servo in bus.servos]))
  kind = rng.integers(10)
  if kind == 0:
    bus.faults.mute_next(motor_id, int(rng.integers(1, 4)))
  elif kind == 1:
    bus.faults.corrupt_next(motor_id, int(rng.integers(1, 3)))
  elif kind == 2:
    bus.faults.lose_next_write(motor_id, int(rng.integers(1, 3)))
  elif kind == 3:
    bus.faults.set_absent(motor_id, bool(rng.integers(2)))


def soak(robot: str, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
  """Step times (s) of the steps that went through, and of those that
  faulted."""
  env = suite.load(
    robot, _TASKS[robot], seed=seed, robot=suite.RobotOptions('virtual')
  )
  bus, rng = env.virtual_bus, np.random.default_rng(seed)
  stepped, faulted = [], []
  try:
    env.reset()
    size = env.action_spec().shape
    for _ in range(steps):
      _inject_random_fault(bus, rng)
      start = time.monotonic()
      try:
        last = env.step(rng.uniform(-1, 1, size)).last()
        stepped.append(time.monotonic() - start)
      except dynamixel.DynamixelError:
        faulted.append(time.monotonic() - start)
        bus.faults.clear()
        last = True
      if last:
        env.reset()
  finally:
    env.close()
  return np.array(stepped), np.array(faulted)


def standalone(seconds: float) -> tuple[np.ndarray, list[str]]:
  """Read times (s) of a D'Claw client at 20 Hz, and the errors."""
  ids = config_lib.default('dclaw').joint_ids
  rng = np.random.default_rng(0)
  times, errors = [], []
  with virtual.standalone_bus('dclaw') as device_path:
    client = dynamixel.DynamixelClient(device_path, ids)
    with client:
      client.set_torque(ids, True)
      end = time.monotonic() + seconds
      tick = time.monotonic()
      while time.monotonic() < end:
        client.write_goal_positions(np.pi + rng.uniform(-0.3, 0.3, len(ids)))
        start = time.monotonic()
        try:
          client.read_state()
          times.append(time.monotonic() - start)
        except dynamixel.DynamixelError as error:
          errors.append(str(error))
        tick += 1 / _RATE_HZ
        time.sleep(max(0.0, tick - time.monotonic()))
  return np.array(times), errors


def _row(name: str, times: np.ndarray) -> str:
  if not times.size:
    return f'  {name:<9} none'
  return (
    f'  {name:<9} {times.size:>5} steps  p50 {np.median(times) * 1e3:6.0f} ms'
    f'  p99 {np.percentile(times, 99) * 1e3:6.0f} ms'
    f'  max {times.max():5.2f} s  >= 1 s: {(times >= 1).sum()}'
  )


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--steps', type=int, default=1000)
  parser.add_argument('--seconds', type=float, default=120.0)
  parser.add_argument('--seed', type=int, default=0)
  args = parser.parse_args()
  logging.disable(logging.CRITICAL)  # The faults' logged errors.
  cores = os.cpu_count()
  print(f'load average {os.getloadavg()[0]:.1f} on {cores} cores')
  for robot in _TASKS:
    stepped, faulted = soak(robot, args.steps, args.seed)
    print(f'{robot} in-process, random faults:')
    print(_row('stepped', stepped))
    print(_row('faulted', faulted), flush=True)
  times, errors = standalone(args.seconds)
  late = (times > _SDK_DEADLINE_S).sum()
  print(
    f'dclaw standalone (sim, {_RATE_HZ} Hz, {args.seconds:.0f} s): '
    f'{times.size} reads, p50 {np.median(times) * 1e3:.1f} ms, '
    f'p99 {np.percentile(times, 99) * 1e3:.1f} ms, max {times.max():.2f} s; '
    f'{late} later than the SDK deadline (waited for); '
    f'{len(errors)} failed'
  )
  for error in errors[:5]:
    print(f'  {error}')
  print(f'load average {os.getloadavg()[0]:.1f} on {cores} cores')


if __name__ == '__main__':
  main()
