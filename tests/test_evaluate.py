"""Tests of the evaluation CLI and its policies."""

import json
import os
import signal
import subprocess
import sys
import time

import child_signals
import numpy as np
import pytest

from robel_dm import assets, evaluation, policies, suite, video
from robel_dm.evaluation import task_args


@pytest.mark.slow
@pytest.mark.parametrize('task', ['pose_fixed', 'pose_random'])
def test_reference_controller_solves_pose(task):
  results = evaluation.evaluate(
    evaluation.EvalConfig('dclaw', task, episodes=20, policy='reference')
  )
  assert results['success_rate'] >= 0.9
  assert results['mean_score'] > 0.7
  # It moves the joints slower than the velocity safety limit.
  assert results['safety']['velocity'] == 0


@pytest.mark.slow
def test_reference_controller_makes_the_dkitty_stand():
  results = evaluation.evaluate(
    evaluation.EvalConfig(
      'dkitty', 'stand_fixed', episodes=20, policy='reference'
    )
  )
  assert results['episodes'] == len(results['records']) == 20
  assert results['success_rate'] >= 0.9
  # It never falls: every episode runs its 80 steps.
  assert [r['steps'] for r in results['records']] == [80] * 20
  # It ends standing straight: the score is about 1 at the last step.
  assert results['mean_final_score'] > 0.9
  assert results['safety']['velocity'] == 0


@pytest.mark.slow
@pytest.mark.parametrize(
  'domain, task', [('dclaw', 'turn_random'), ('dkitty', 'walk_random')]
)
def test_metrics_match_a_manual_rollout(domain, task):
  seed = 3
  results = evaluation.evaluate(
    evaluation.EvalConfig(domain, task, episodes=2, policy='zero', seed=seed)
  )
  env = suite.load(domain, task, seed=seed)
  zeros = np.zeros(env.action_spec().shape)
  returns, successes, safety, steps = [], [], np.zeros(3), []
  for episode in range(2):
    env.random_state.seed(seed + episode)  # Episode i's seed: seed + i.
    timestep = env.reset()
    total, count = 0.0, 0
    while not timestep.last():
      timestep = env.step(zeros)
      total += timestep.reward
      safety += timestep.observation['safety']
      count += 1
    returns.append(total)
    successes.append(bool(timestep.observation['success']))
    steps.append(count)
  assert results['mean_return'] == pytest.approx(np.mean(returns), abs=1e-9)
  assert results['success_rate'] == np.mean(successes)
  assert list(results['safety'].values()) == pytest.approx(safety / 2)
  assert [r['steps'] for r in results['records']] == steps
  if domain == 'dclaw':
    assert steps == [40, 40]
  assert results['steps_per_second'] > 0
  assert [r['seed'] for r in results['records']] == [seed, seed + 1]
  assert results['provenance']['versions']['mujoco'] == '3.17.0'
  spread = results['spread']['return']
  assert spread['mean'] == pytest.approx(np.mean(returns))
  assert spread['ci95'][0] <= spread['mean'] <= spread['ci95'][1]


def test_random_policy_is_seeded_and_inside_the_bounds():
  env = suite.load('dclaw', 'pose_fixed', seed=0)
  first = policies.make_policy('random', env, seed=5)
  second = policies.make_policy('random', env, seed=5)
  timestep = env.reset()
  actions = [first(timestep) for _ in range(50)]
  assert np.array_equal(actions[0], second(timestep))
  assert np.all(np.abs(actions) <= 1.0)
  assert not np.array_equal(actions[0], actions[1])


@pytest.mark.slow
def test_unknown_or_unavailable_policies_raise():
  env = suite.load('dclaw', 'turn_fixed', seed=0)
  with pytest.raises(ValueError, match='no scripted reference'):
    policies.make_policy('reference', env, seed=0)
  for task in ('orient_fixed', 'walk_fixed'):
    kitty_env = suite.load('dkitty', task, seed=0)
    with pytest.raises(ValueError, match='no scripted reference'):
      policies.make_policy('reference', kitty_env, seed=0)
  with pytest.raises(ValueError, match="unknown policy 'greedy'"):
    policies.make_policy('greedy', env, seed=0)


@pytest.mark.parametrize(
  'text, expected',
  [
    ('', {}),
    ('{"valve": "valve4"}', {'valve': 'valve4'}),
    ('valve=valve4', {'valve': 'valve4'}),
    ('valve=valve4,action_bounds=clip',
     {'valve': 'valve4', 'action_bounds': 'clip'}),
    ('episode_steps=10', {'episode_steps': 10}),
  ],
)  # fmt: skip
def test_parse_task_kwargs(text, expected):
  assert task_args.parse_task_kwargs(text) == expected


@pytest.mark.parametrize('text', ['{"valve": ', '[1, 2]', 'valve', '=x'])
def test_parse_task_kwargs_rejects_malformed_text(text):
  with pytest.raises(ValueError, match='task_kwargs'):
    task_args.parse_task_kwargs(text)


def _run_cli(*flags, cwd):
  env = dict(os.environ, MUJOCO_GL='egl')
  return subprocess.run(
    preexec_fn=child_signals.default,
    args=[sys.executable, '-m', 'robel_dm.commands.evaluate', *flags],
    capture_output=True, text=True, cwd=cwd, env=env,
  )  # fmt: skip


@pytest.mark.slow
def test_cli_prints_a_table_and_writes_json(tmp_path):
  output = tmp_path / 'results.json'
  result = _run_cli(
    '--domain=dclaw', '--task=screw_fixed', '--policy=random',
    '--episodes=2', '--task_kwargs=valve=valve4', f'--output={output}',
    cwd=tmp_path,
  )  # fmt: skip
  assert result.returncode == 0, result.stderr
  assert 'success rate' in result.stdout
  results = json.loads(output.read_text())
  for key in (
    'domain', 'task', 'episodes', 'success_rate', 'mean_return',
    'mean_score', 'safety', 'steps_per_second',
  ):  # fmt: skip
    assert key in results
  assert results['task_kwargs'] == {'valve': 'valve4'}
  assert set(results['safety']) == {'position', 'velocity', 'current'}
  assert results['episodes'] == len(results['records']) == 2
  assert results['complete'] and results['episodes_requested'] == 2
  assert 'interrupted' not in results


@pytest.mark.slow
def test_cli_evaluates_a_dkitty_task(tmp_path):
  output = tmp_path / 'results.json'
  result = _run_cli(
    '--domain=dkitty', '--task=stand_fixed', '--policy=reference',
    '--episodes=2', f'--output={output}', cwd=tmp_path,
  )  # fmt: skip
  assert result.returncode == 0, result.stderr
  assert 'dkitty/stand_fixed' in result.stdout
  assert 'success rate' in result.stdout
  results = json.loads(output.read_text())
  assert (results['domain'], results['task']) == ('dkitty', 'stand_fixed')
  assert results['episodes'] == len(results['records']) == 2
  assert [r['steps'] for r in results['records']] == [80, 80]
  assert results['success_rate'] == 1.0


@pytest.mark.slow
@pytest.mark.parametrize(
  'flags, message',
  [
    (['--task=turn_fixd'], "unknown dclaw task 'turn_fixd'"),
    (
      ['--domain=dkitty', '--task=turn_fixed'],
      "unknown dkitty task 'turn_fixed'",
    ),
    (
      ['--domain=dkitty', '--task=walk_fixed', '--policy=reference'],
      'no scripted reference',
    ),
    (['--domain=dcat'], "unknown domain 'dcat'"),
    (['--task=turn_fixed', '--policy=reference'], 'no scripted reference'),
    (['--task=turn_fixed', '--task_kwargs=valve=valve5'], 'unknown valve'),
    (['--policy=greedy'], 'policy'),
    (['--episodes=0'], 'episodes'),
  ],
)
def test_cli_rejects_bad_input_with_a_clear_message(flags, message, tmp_path):
  result = _run_cli(*flags, cwd=tmp_path)
  assert result.returncode != 0
  assert message in result.stderr


@pytest.mark.slow
def test_cli_lists_the_tasks(tmp_path):
  result = _run_cli('--list', cwd=tmp_path)
  assert result.returncode == 0, result.stderr
  assert 'dclaw' in result.stdout and 'walk_random_dynamics' in result.stdout


def _sweep(tmp_path, domain, policy):
  """A one-episode sweep of every task of `domain`: the finished process
  and the results it wrote."""
  output = tmp_path / 'sweep.json'
  result = _run_cli(
    f'--domain={domain}', '--task=all', '--episodes=1', f'--policy={policy}',
    f'--output={output}', cwd=tmp_path,
  )  # fmt: skip
  assert result.returncode == 0, result.stderr
  return result, json.loads(output.read_text())


@pytest.mark.slow
def test_cli_sweeps_every_task(tmp_path):
  result, results = _sweep(tmp_path, 'all', 'zero')
  assert [(r['domain'], r['task']) for r in results] == list(suite.ALL_TASKS)
  assert all(r['episodes'] == 1 for r in results)
  # Each task's rows are printed as its episodes end.
  assert result.stdout.count('success rate') == len(suite.ALL_TASKS)


@pytest.mark.slow
def test_cli_checks_the_output_path_before_the_first_episode(tmp_path):
  result = _run_cli(
    '--episodes=1', f'--output={tmp_path}/missing/results.json', cwd=tmp_path
  )
  assert result.returncode == 2
  assert 'no folder' in result.stderr and 'episode' not in result.stdout


@pytest.mark.slow
def test_ctrl_c_mid_sweep_keeps_every_finished_episode(tmp_path):
  output = tmp_path / 'sweep.json'
  process = subprocess.Popen(
    preexec_fn=child_signals.default,
    args=[sys.executable, '-m', 'robel_dm.commands.evaluate', '--domain=dclaw',
     '--task=all', '--episodes=20', '--policy=zero', f'--output={output}'],
    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    env=dict(os.environ, MUJOCO_GL='egl'),
  )  # fmt: skip
  deadline = time.monotonic() + 60
  while not output.exists() and time.monotonic() < deadline:
    time.sleep(0.05)
  time.sleep(0.5)  # A few more episodes.
  process.send_signal(signal.SIGINT)
  _, errors = process.communicate(timeout=60)
  assert process.returncode == 130, errors
  saved = json.loads(output.read_text())  # Valid JSON.
  saved = saved if isinstance(saved, list) else [saved]
  episodes = sum(r['episodes'] for r in saved)
  assert 1 <= episodes < 20 * 9
  assert all(len(r['records']) == r['episodes'] for r in saved)
  # The file says the run was cut short, and where.
  assert saved[-1]['interrupted'] is True
  assert all(r['complete'] for r in saved[:-1])
  assert not any(r.get('interrupted') for r in saved[:-1])
  assert 'marked interrupted' in errors


@pytest.mark.slow
def test_a_reference_sweep_skips_tasks_without_a_controller(tmp_path):
  result, results = _sweep(tmp_path, 'dkitty', 'reference')
  assert 'skipped dkitty/walk_fixed: no reference controller' in result.stderr
  ran = [r['task'] for r in results]
  assert ran == ['stand_fixed', 'stand_random', 'stand_random_dynamics']


@pytest.mark.slow
def test_a_baseline_sweep_skips_tasks_without_a_shipped_policy(tmp_path):
  result, results = _sweep(tmp_path, 'dkitty', 'baseline')
  shipped = {
    p.stem.split('_', 1)[1] for p in assets.baselines_dir().glob('dkitty_*')
  }
  ran = {r['task'] for r in results}
  assert ran == shipped
  for task in set(suite.TASKS_BY_DOMAIN['dkitty']) - shipped:
    assert f'skipped dkitty/{task}: no shipped baseline' in result.stderr


@pytest.mark.slow
def test_only_the_chosen_episodes_are_filmed(tmp_path, monkeypatch):
  pytest.importorskip('imageio_ffmpeg', reason='needs robel_dm[video]')
  frames = []
  monkeypatch.setattr(
    video, 'render',
    lambda env, camera, size=(4, 4): frames.append(camera) or np.zeros(
      (240, 320, 3), np.uint8),
  )  # fmt: skip
  lines = []
  results = evaluation.evaluate(evaluation.EvalConfig(
    'dclaw', 'pose_fixed', 3, policy='zero', video_dir=str(tmp_path),
    video_episodes=[1], log=lines.append,
  ))  # fmt: skip
  assert sorted(p.name for p in tmp_path.iterdir()) == [
    'dclaw_pose_fixed_0001.mp4'
  ]
  assert [('video' in r) for r in results['records']] == [False, True, False]
  assert lines and lines[0].startswith('videos: camera ')
  assert 's a frame here' in lines[0] and 'MUJOCO_GL=' in lines[0]


@pytest.mark.slow
@pytest.mark.parametrize(
  'flags, message',
  [
    (['--video_episodes=0'], '--video_episodes needs --video=DIR'),
    (['--video=v', '--video_episodes=3', '--episodes=2'], 'from 0 to 1'),
    (['--video=v', '--video_episodes=a'], 'give episode indices'),
  ],
)
def test_bad_video_episodes_are_refused_in_one_line(flags, message, tmp_path):
  result = _run_cli(*flags, cwd=tmp_path)
  assert result.returncode == 2
  assert message in result.stderr and 'Traceback' not in result.stderr
  assert not (tmp_path / 'v').exists()


@pytest.mark.slow
@pytest.mark.parametrize('policy', ['random', 'zero'])
def test_workers_give_the_same_episodes_as_a_serial_run(policy):
  serial = evaluation.evaluate(
    evaluation.EvalConfig('dclaw', 'turn_random', 4, policy=policy, seed=7)
  )
  parallel = evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'turn_random', 4, policy=policy, seed=7, workers=2
    )
  )
  assert parallel['records'] == serial['records']
  assert parallel['success_rate'] == serial['success_rate']


def test_workers_refuse_what_they_cannot_share(tmp_path):
  with pytest.raises(ValueError, match='not with a policy given as an object'):
    evaluation.evaluate(
      evaluation.EvalConfig(
        'dclaw', 'pose_fixed', 2, policy=lambda t: np.zeros(9), workers=2
      )
    )
  with pytest.raises(ValueError, match='not with recording'):
    evaluation.EvalConfig(
      'dclaw', 'pose_fixed', 2, policy='zero', workers=2, record=tmp_path
    )


@pytest.mark.slow
def test_a_local_ray_instance_gives_the_same_episodes_as_a_serial_run():
  pytest.importorskip('ray', reason='needs robel_dm[scale]')
  serial = evaluation.evaluate(
    evaluation.EvalConfig('dclaw', 'pose_random', 3, policy='random', seed=2)
  )
  on_ray = evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw', 'pose_random', 3, policy='random', seed=2, ray_address='local'
    )
  )
  assert on_ray['records'] == serial['records']


def test_a_policy_is_refused_on_a_task_of_another_action_map():
  # The shipped Pose Random policy learned through the safe map; on a task
  # built with ROBEL's it would act through a map it never learned.
  env = suite.load('dclaw', 'pose_random', seed=0)
  with pytest.raises(policies.PolicyError, match='learned through the safe'):
    policies.make_policy('baseline', env, 0, 'dclaw', 'pose_random', {})
  env = suite.load(
    'dclaw', 'pose_random', seed=0, task_kwargs={'action_map': 'safe'}
  )
  policy = policies.make_policy(
    'baseline', env, 0, 'dclaw', 'pose_random', {'action_map': 'safe'}
  )
  assert policy.action_map == 'safe'
