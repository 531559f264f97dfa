"""System identification where the truth is known, and the cost of a delay.

1. Recovery. For each robot and excitation signal, a virtual bus runs a robot
   whose every joint has kp, damping and armature scaled by its own random
   factor in [0.6, 1.6], friction loss 0.02 N m (`--friction=high`; the
   model has none) or each joint's own in [0.002, 0.004] N m
   (`--friction=low`) and a 7.5 ms control delay. The excitation is
   recorded through dynamixel_sdk and fitted, with and without the
   measured currents. Prints, per parameter, the largest relative error
   over the joints, the delay found, the RMS angle error before and after,
   and the fit's time.
2. Uncertainty. Per run and parameter: the joint whose true error is the
   most reported standard errors (SE) away, its error, SE and their ratio,
   and in how many joints the true error is within 2 SEs; then the same
   over all runs, and how many values are flagged as poorly determined.
3. Step cost. `env.step` of pose_fixed with and without a calibrated delay,
   each against raw MuJoCo stepping the same trajectory in the same run.

    MUJOCO_GL=egl python benchmarks/sysid.py [--seeds 3] [--duration 10] \
      [--friction high,low] [--domains dclaw,dkitty] [--signals steps,chirp] \
      [--currents yes,no] [--rounds 7]   # --rounds 0: no step cost
"""

import argparse
import tempfile
import time

import mujoco
import numpy as np

from robel_dm import calibration, recording, suite
from robel_dm.sysid import excite, fit

# Friction loss of the truth's joints, N m: one value, or a range each
# joint draws its own value from.
FRICTIONLOSS = {'high': 0.02, 'low': (0.002, 0.004)}
DELAY = 0.0075  # s
# A fitted value further off than this counts as wrong; the report should
# flag every wrong value (`unflagged` counts those it does not).
TOLERANCE = 0.15


def _truth(domain: str, seed: int, friction: str) -> calibration.Calibration:
  # The model's values, per joint, drawn around.
  simulator = fit.ReplaySimulator(domain)
  names, nominal = simulator.joint_names, simulator.nominal
  rng = np.random.default_rng(seed)
  factors = rng.uniform(0.6, 1.6, (len(names), 3))
  frictionloss = np.broadcast_to(
    rng.uniform(*FRICTIONLOSS[friction], len(names))
    if friction == 'low'
    else FRICTIONLOSS[friction],
    len(names),
  )
  joints = {
    name: {
      'kp': float(nominal['kp'][i] * f[0]),
      'damping': float(nominal['damping'][i] * f[1]),
      'armature': float(nominal['armature'][i] * f[2]),
      'frictionloss': float(loss),
    }
    for i, (name, f, loss) in enumerate(
      zip(names, factors, frictionloss, strict=True)
    )
  }
  return calibration.Calibration(domain, joints, control_delay=DELAY)


def recovery(domain, signal, seed, duration, use_current, friction) -> dict:
  truth = _truth(domain, seed, friction)
  with tempfile.TemporaryDirectory() as directory:
    env = suite.load_excitation(
      domain,
      duration,
      seed=seed,
      dynamics=truth,
      robot=suite.RobotOptions('virtual'),
    )
    metadata = {'kind': 'excitation', 'domain': domain}
    env = recording.Recorder(env, directory, metadata=metadata)
    try:
      excite.run(env, excite.Excitation(signal, duration, seed=seed))
    finally:
      env.close()
    trajectories = fit.load_trajectories(directory, domain)
  if not use_current:
    for trajectory in trajectories:
      trajectory.current = None
  start = time.perf_counter()
  result = fit.fit(trajectories, domain)
  seconds = time.perf_counter() - start
  errors, unflagged, uncertainty = {}, 0, {}
  names = result.joint_names
  for name, values in result.fitted.items():
    true = np.array([truth.joints[j][name] for j in result.joint_names])
    relative = np.abs(values / true - 1)
    errors[name] = float(np.max(relative))
    # True error in reported standard errors, per joint.
    ratio = np.abs(values - true) / result.standard_error[name]
    flagged = [f'{j}.{name}' in result.not_identified for j in names]
    worst = int(np.argmax(ratio))
    uncertainty[name] = {
      'ratios': ratio.tolist(),
      'errors': relative.tolist(),
      'flagged': flagged,
      'worst': (
        result.joint_names[worst],
        float(relative[worst]),
        float(result.uncertainty[name][worst]),
        float(ratio[worst]),
      ),
    }
    unflagged += sum(
      error > TOLERANCE and f'{joint}.{name}' not in result.not_identified
      for joint, error in zip(result.joint_names, relative, strict=True)
    )
  return {
    'errors': errors,
    'uncertainty': uncertainty,
    'delay_ms': result.control_delay * 1e3,
    'rms_before_deg': float(np.degrees(np.sqrt(np.mean(result.rms_before**2)))),
    'rms_after_deg': float(np.degrees(np.sqrt(np.mean(result.rms_after**2)))),
    'worst_ratio': float(np.max(result.rms_after / result.rms_before)),
    'not_identified': len(result.not_identified),
    'unflagged': unflagged,
    'seconds': seconds,
    'simulations': result.evaluations,
  }


def step_cost(steps: int, rounds: int) -> dict:
  """Seconds per env.step with and without a delay, and raw MuJoCo's."""
  delayed = calibration.Calibration(
    'dclaw', {'FFJ10': {'kp': 2.0}}, control_delay=DELAY
  )
  results = {}
  for label, dynamics in (('no delay', None), ('7.5 ms delay', delayed)):
    env = suite.load('dclaw', 'pose_fixed', seed=0, dynamics=dynamics)
    env.reset()
    actions = np.random.default_rng(0).uniform(-1, 1, (steps, 9))
    model, data = env.physics.model.ptr, env.physics.data.ptr
    start_state = mujoco.MjData(model)
    best_env = best_raw = np.inf
    for _ in range(rounds):
      env.reset()
      mujoco.mj_copyData(start_state, model, data)
      controls = np.empty((steps, model.nu))
      start = time.perf_counter()
      for i, action in enumerate(actions):
        env.step(action)
        controls[i] = data.ctrl
      best_env = min(best_env, (time.perf_counter() - start) / steps)
      mujoco.mj_copyData(data, model, start_state)
      substeps = env.task.physics_steps_per_control_step
      start = time.perf_counter()
      for control in controls:
        data.ctrl[:] = control
        mujoco.mj_step(model, data, substeps)
      best_raw = min(best_raw, (time.perf_counter() - start) / steps)
    results[label] = (best_env, best_raw)
    env.close()
  return results


def _coverage_row(label, data) -> str:
  """Uncertainty of one run and parameter (data: recovery's)."""
  joint, error, se, ratio = data['worst']
  ratios = np.array(data['ratios'])
  return (
    f'| {label} | {joint} | {error:.1%} | {se:.1%} | {ratio:.1f} | '
    f'{np.sum(ratios <= 2)}/{len(ratios)} | {sum(data["flagged"])} |'
  )


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument('--seeds', type=int, default=3)
  parser.add_argument('--duration', type=float, default=10.0)
  parser.add_argument('--friction', default='high,low')
  parser.add_argument('--domains', default='dclaw,dkitty')
  parser.add_argument('--signals', default=','.join(excite.SIGNALS))
  parser.add_argument('--currents', default='yes,no')
  parser.add_argument('--steps', type=int, default=400)
  parser.add_argument('--rounds', type=int, default=7)
  arguments = parser.parse_args()
  print(
    '| robot | signal | currents | friction | seed | max error kp | damping | '
    'friction loss | armature | delay ms | RMS deg before -> after (worst '
    'joint after/before) | flagged | off >15% unflagged | fit s '
    '(simulations) |'
  )
  print('|' + '---|' * 14)
  runs = []
  for domain in arguments.domains.split(','):
    for signal in arguments.signals.split(','):
      for currents in arguments.currents.split(','):
        for friction in arguments.friction.split(','):
          for seed in range(1, arguments.seeds + 1):
            r = recovery(
              domain, signal, seed, arguments.duration, currents == 'yes',
              friction,
            )  # fmt: skip
            label = f'{domain} | {signal} | {currents} | {friction} | {seed}'
            runs.append((label, r))
            e = r['errors']
            print(
              f'| {label} | {e["kp"]:.1%} | {e["damping"]:.1%} | '
              f'{e["frictionloss"]:.1%} | {e["armature"]:.1%} | '
              f'{r["delay_ms"]:.1f} | {r["rms_before_deg"]:.3f} -> '
              f'{r["rms_after_deg"]:.4f} ({r["worst_ratio"]:.3f}) | '
              f'{r["not_identified"]} | {r["unflagged"]} | '
              f'{r["seconds"]:.1f} ({r["simulations"]}) |',
              flush=True,
            )
  print(
    '\nUncertainty: per run and parameter, the joint whose true error is the '
    'most standard errors (SE) away; errors and SEs relative to the value.\n'
  )
  print(
    '| robot | signal | currents | friction | seed | parameter | joint | '
    'true error | reported SE | error/SE | within 2 SE | flagged |'
  )
  print('|' + '---|' * 12)
  total: dict[str, list] = {}
  for label, r in runs:
    for name, data in r['uncertainty'].items():
      print(_coverage_row(f'{label} | {name}', data))
      total.setdefault(name, []).append(data)
  print('\nOver all runs (joint values):')
  for name, data in total.items():
    ratios = np.concatenate([d['ratios'] for d in data])
    flagged = np.concatenate([d['flagged'] for d in data])
    wrong = np.concatenate([d['errors'] for d in data]) > TOLERANCE
    print(
      f'  {name:<13} true error within 2 SE in {np.sum(ratios <= 2)} of '
      f'{len(ratios)}, within 3 SE in {np.sum(ratios <= 3)}; median '
      f'error/SE {np.median(ratios):.2f}, largest {np.max(ratios):.1f}; '
      f'flagged {int(np.sum(flagged))}, off >15% {int(np.sum(wrong))} '
      f'(unflagged {int(np.sum(wrong & ~flagged))})'
    )
  if arguments.rounds <= 0:
    return
  print('\nenv.step of dclaw pose_fixed against raw MuJoCo (same trajectory):')
  for label, (env_s, raw_s) in step_cost(
    arguments.steps, arguments.rounds
  ).items():
    print(
      f'  {label:<13} {env_s * 1e6:7.1f} us/step, raw {raw_s * 1e6:7.1f} '
      f'us/step, ratio raw/env {raw_s / env_s:.3f}'
    )


if __name__ == '__main__':
  main()
