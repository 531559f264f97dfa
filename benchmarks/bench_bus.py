"""Control-loop timing on the virtual servo bus (9 and 12 motors).

Starts the virtual bus as a separate process (`--driver=ideal`: replies come
at once, so its own time is the pty round trip), then for the D'Claw (9
motors) and the D'Kitty (12):
  * bus time: one control step's transactions alone (sync write of the goal
    positions + sync read of current, velocity, position), in a tight loop;
  * a real-time episode through `HardwareEnvironment.step` (D'Claw Pose at
    20 Hz, D'Kitty Stand at 10 Hz): the software overhead per step (step
    time minus its bus transactions, the periodic health reads included,
    minus the wait for the tick) and the jitter of the control period
    (start-to-start of the motor exchanges, against the task's period).
Prints them next to the physical bus's time per step at 1 Mbps (wire bytes
at 10 bits per byte, Return Delay Time 0; docs/dynamixel.md section 5).

    MUJOCO_GL=egl python benchmarks/bench_bus.py [--steps 100]
"""

import argparse
import time

import numpy as np

from robel_dm import suite
from robel_dm.entities import dkitty
from robel_dm.hardware import config as config_lib
from robel_dm.hardware import environment as hardware
from robel_dm.hardware import options, virtual
from robel_dm.hardware.dynamixel import client as dynamixel
from robel_dm.hardware.dynamixel import control_table as table

# Wire bytes of one step at 1 Mbps (docs/dynamixel.md section 5): sync-read
# instruction 14 + N, N status replies of 11 bytes + the state block (goal
# read-back, current, velocity, position), sync write 14 + 5 N.
_BAUD = table.DEFAULT_BAUD_RATE
_TASKS = {'dclaw': 'pose_fixed', 'dkitty': 'stand_fixed'}


def physical_bus_ms(motors: int) -> float:
  reply = 11 + table.STATE_BLOCK_SIZE
  wire_bytes = (14 + motors) + reply * motors + (14 + 5 * motors)
  return wire_bytes * 10 / _BAUD * 1e3


def bus_time(device_path: str, robot: str, count: int) -> np.ndarray:
  config = config_lib.default(robot)
  ids = config.joint_ids
  with dynamixel.DynamixelClient(device_path, ids) as client:
    client.set_torque(ids, True)
    goals = np.full(len(ids), np.pi)
    times = []
    for _ in range(count):
      start = time.perf_counter()
      client.write_goal_positions(goals)
      client.read_state()
      times.append(time.perf_counter() - start)
  return np.array(times)


class _Timed:
  """Wraps a callable and adds up its run time."""

  def __init__(self, function):
    self.function, self.total = function, 0.0

  def __call__(self, *args, **kwargs):
    start = time.perf_counter()
    try:
      return self.function(*args, **kwargs)
    finally:
      self.total += time.perf_counter() - start


def control_loop(device_path: str, robot: str, steps: int) -> dict:
  task = suite.registry.DOMAINS[robot][_TASKS[robot]]()
  standing = (
    dkitty.ROBEL_FRAME_ORIGIN, np.array([1.0, 0, 0, 0]), np.zeros(3),
    np.zeros(3),
  )  # fmt: skip
  env = hardware.make_environment(
    task,
    domain=robot,
    robot=options.RobotOptions(device_path),
    torso_source=(lambda: standing) if task.root_joint is not None else None,
    time_limit=float('inf'),
  )
  try:
    env.reset()
    client, physics = env.robot.client, env.physics
    # Every bus transaction of a step: state read, goal write, and every
    # tenth step the hardware-error and temperature reads.
    read = client.read_state = _Timed(client.read_state)
    write = client.write_goal_positions = _Timed(client.write_goal_positions)
    health = client.sync_read_register = _Timed(client.sync_read_register)
    clock = physics.clock
    sleep = clock.sleep_until = _Timed(clock.sleep_until)
    exchanges = []
    original_read = physics._read_motors  # noqa: SLF001

    def read_motors():
      exchanges.append(time.perf_counter())
      original_read()

    physics._read_motors = read_motors  # noqa: SLF001
    action = task.normalize_joint_targets(
      dkitty.STANDING_POSE if robot == 'dkitty' else np.zeros(9)
    )
    overheads = []
    for _ in range(steps):
      before = read.total + write.total + health.total + sleep.total
      start = time.perf_counter()
      env.step(action)
      elapsed = time.perf_counter() - start
      spent = read.total + write.total + health.total + sleep.total - before
      overheads.append(elapsed - spent)
    periods = np.diff(exchanges[1:])  # The first period starts at reset.
    return {
      'overhead_ms': np.array(overheads) * 1e3,
      'jitter_ms': np.abs(periods - task.control_timestep) * 1e3,
    }
  finally:
    env.close()


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--steps', type=int, default=100)
  parser.add_argument('--transactions', type=int, default=1000)
  args = parser.parse_args()
  print(
    f'{"robot":<7} {"motors":>6} {"bus p50 ms":>10} {"bus p99":>8} '
    f'{"1 Mbps wire":>11} {"overhead p50":>12} {"p99":>6} '
    f'{"jitter p50":>10} {"p99":>6} {"max":>6}'
  )
  for robot in ('dclaw', 'dkitty'):
    motors = len(config_lib.default(robot).joints)
    with virtual.standalone_bus(robot, driver='ideal') as device_path:
      bus = bus_time(device_path, robot, args.transactions) * 1e3
      loop = control_loop(device_path, robot, args.steps)
    overhead, jitter = loop['overhead_ms'], loop['jitter_ms']
    print(
      f'{robot:<7} {motors:>6} {np.median(bus):>10.2f} '
      f'{np.percentile(bus, 99):>8.2f} {physical_bus_ms(motors):>11.2f} '
      f'{np.median(overhead):>12.2f} {np.percentile(overhead, 99):>6.2f} '
      f'{np.median(jitter):>10.2f} {np.percentile(jitter, 99):>6.2f} '
      f'{jitter.max():>6.2f}',
      flush=True,
    )


if __name__ == '__main__':
  main()
