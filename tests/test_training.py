"""Training runs: agents, artefacts, evaluations, best policies, resume."""

import dataclasses
import json
import pathlib
import pickle

import numpy as np
import pytest

pytest.importorskip('stable_baselines3', reason='needs robel_dm[learn]')
pytest.importorskip('sbx', reason='needs robel_dm[learn]')

from robel_dm import evaluation, policies, provenance  # noqa: E402
from robel_dm.learning import agents, demos  # noqa: E402
from robel_dm.learning import training as learning  # noqa: E402

QUIET = {'log': lambda line: None}


def _config(**changes) -> learning.RunConfig:
  base = learning.RunConfig(
    domain='dclaw',
    task='pose_random',
    steps=304,
    eval_every=152,
    eval_episodes=1,
    hidden=(16, 16),
    safety_penalty=0.5,
  )
  return dataclasses.replace(base, **changes)


@pytest.fixture(scope='module')
def trained_run(tmp_path_factory):
  output = tmp_path_factory.mktemp('run')
  history = learning.train(_config(), output, **QUIET)
  return output, history


@pytest.mark.slow
def test_training_writes_every_artefact(trained_run):
  output, history = trained_run
  for name in ('checkpoint.zip', 'replay_buffer.pkl', 'env_state.pkl',
               'policy.npz', 'policy_best.npz', 'eval.jsonl',
               'learning_curve.png', 'config.json',
               'metadata.json'):  # fmt: skip
    assert (output / name).is_file(), name
  rows = [json.loads(line) for line in (output / 'eval.jsonl').open()]
  # An evaluation of the untrained actor first, then one per chunk; the
  # default agent collects 8 steps between updates.
  assert [row['env_steps'] for row in rows][0] == 0
  assert [row['env_steps'] for row in rows][-1] == 304
  assert rows == json.loads(json.dumps(history))
  assert set(rows[0]) >= {'env_steps', 'wall_time', 'cpu_time',
                          'success_rate', 'mean_score', 'mean_return',
                          'safety', 'episodes'}  # fmt: skip
  assert set(rows[0]['safety']) == {'position', 'velocity', 'current'}
  config = json.loads((output / 'config.json').read_text())
  assert config['safety_penalty'] == 0.5 and config['steps'] == 304
  assert config['algo'] == agents.DEFAULT == 'sac'


@pytest.mark.slow
def test_the_best_evaluated_policy_is_kept(tmp_path, monkeypatch):
  # Evaluations that rise then fall: the best file holds the second actor.
  scores = iter([0.1, 0.9, 0.2])

  def fake_evaluate(policy, config, episodes, evaluations=None):
    score = next(scores)
    fake_evaluate.seen.append((score, policy.act(np.zeros(27))))
    return {'success_rate': 0.0, 'mean_score': score, 'mean_return': 0.0,
            'safety': {'position': 0.0}, 'episodes': episodes}  # fmt: skip

  fake_evaluate.seen = []
  monkeypatch.setattr(learning, 'evaluate_policy', fake_evaluate)
  learning.train(
    _config(steps=1024, eval_every=512, safety_penalty=0.0), tmp_path, **QUIET
  )
  best = policies.load(tmp_path / 'policy_best.npz').act(np.zeros(27))
  last = policies.load(tmp_path / 'policy.npz').act(np.zeros(27))
  np.testing.assert_allclose(best, fake_evaluate.seen[1][1], rtol=1e-6)
  np.testing.assert_allclose(last, fake_evaluate.seen[2][1], rtol=1e-6)
  assert not np.allclose(best, last)


def test_evaluations_use_seeds_no_training_episode_uses(monkeypatch):
  seen = {}

  def fake(config, **reuse):
    seen['seed'] = config.seed
    return {'success_rate': 0, 'mean_score': 0, 'mean_return': 0,
            'safety': {}}  # fmt: skip

  monkeypatch.setattr(evaluation, 'evaluate', fake)
  config = _config(seed=3, num_envs=4)
  learning.evaluate_policy(None, config, 50)
  training_seeds = {config.seed * 1000 + i for i in range(config.num_envs)}
  evaluation_seeds = set(range(seen['seed'], seen['seed'] + 50))
  assert not training_seeds & evaluation_seeds


@pytest.mark.slow
def test_a_run_builds_one_evaluation_environment(tmp_path, monkeypatch):
  # Three evaluations, one environment and one provenance read; the rows
  # equal those of evaluations that each build their own.
  loads, reads = [], []
  real_load, real_describe = learning.suite.load, provenance.describe

  def load(domain, task, *args, seed=None, **kwargs):
    loads.append(seed)
    return real_load(domain, task, *args, seed=seed, **kwargs)

  def describe():
    reads.append(1)
    return real_describe()

  monkeypatch.setattr(learning.suite, 'load', load)
  monkeypatch.setattr(provenance, 'describe', describe)
  config = _config(eval_episodes=2)
  history = learning.train(config, tmp_path, **QUIET)
  assert len(history) == 3
  assert loads.count(learning._eval_seed(config)) == 1 and len(reads) == 1
  alone = learning.evaluate_policy(
    policies.load(tmp_path / 'policy.npz'), config, 2
  )
  assert alone == {key: history[-1][key] for key in alone}


@pytest.mark.slow
def test_evaluate_in_a_given_environment_equals_a_new_one():
  config = evaluation.EvalConfig('dkitty', 'walk_random_dynamics', 2, seed=7)
  alone = evaluation.evaluate(config)
  env = learning.suite.load('dkitty', 'walk_random_dynamics', seed=1)
  try:
    evaluation.evaluate(dataclasses.replace(config, seed=11), env=env)
    again = evaluation.evaluate(
      config, env=env, provenance_record={'git_revision': 'x'}
    )
    assert again['records'] == alone['records']
    assert again['provenance'] == {'git_revision': 'x'}
    env.step(np.zeros(env.action_spec().shape))  # Left open.
  finally:
    env.close()
  with pytest.raises(ValueError, match='given env'):
    evaluation.evaluate(dataclasses.replace(config, workers=2), env=env)


@pytest.mark.slow
def test_resume_continues_with_every_transition(trained_run):
  output, _ = trained_run
  before = pickle.loads((output / 'replay_buffer.pkl').read_bytes())
  state = pickle.loads((output / 'env_state.pkl').read_bytes())
  history = learning.train(_config(steps=608), output, resume=True, **QUIET)
  steps = [row['env_steps'] for row in history]
  assert steps[0] == 0 and steps[-1] == 608 and steps == sorted(steps)
  after = pickle.loads((output / 'replay_buffer.pkl').read_bytes())
  # The buffer grew to the new budget and kept the first run's transitions.
  assert after.buffer_size >= 608 > before.buffer_size
  held = before.buffer_size if before.full else before.pos
  assert held == 304
  np.testing.assert_array_equal(
    after.observations[:held], before.observations[:held]
  )
  assert (after.pos, after.full) in ((608, False), (0, True))
  # The training episodes went on from the saved random stream: the first
  # episode after resuming is not the run's first episode again.
  assert not np.array_equal(
    after.observations[held, 0], after.observations[0, 0]
  )
  resumed = pickle.loads((output / 'env_state.pkl').read_bytes())
  now, then = resumed[0]['random_state'], state[0]['random_state']
  assert not (np.array_equal(now[1], then[1]) and now[2] == then[2])


@pytest.mark.slow
@pytest.mark.parametrize(
  ('algo', 'cut', 'into_episode'),
  [
    # 520 env steps are 6.5 Pose episodes: SAC stops 40 steps into one,
    # after its first updates (from 500 on), and learns on after resuming.
    ('sac', 520, 40),
    # TRPO (PyTorch: the shared random streams) after its first rollout.
    ('trpo', 2048, 48),
  ],
)
def test_a_run_resumed_mid_episode_equals_one_never_stopped(
  tmp_path, algo, cut, into_episode
):
  whole, stopped = tmp_path / 'whole', tmp_path / 'stopped'
  config = _config(algo=algo, steps=2 * cut, eval_every=cut)
  learning.train(config, whole, **QUIET)
  learning.train(dataclasses.replace(config, steps=cut), stopped, **QUIET)
  saved = pickle.loads((stopped / 'env_state.pkl').read_bytes())
  assert len(saved[0]['actions']) == into_episode
  learning.train(config, stopped, resume=True, **QUIET)
  for name in ('policy.npz', 'policy_best.npz'):
    a, b = np.load(whole / name), np.load(stopped / name)
    assert a.files == b.files
    for key in a.files:
      np.testing.assert_array_equal(a[key], b[key], err_msg=f'{name} {key}')
  rows = [
    [json.loads(line) for line in (run / 'eval.jsonl').open()]
    for run in (whole, stopped)
  ]
  keep = ('env_steps', 'success_rate', 'mean_score', 'mean_return', 'safety')
  assert [{k: r[k] for k in keep} for r in rows[0]] == [
    {k: r[k] for k in keep} for r in rows[1]
  ]


@pytest.mark.slow
@pytest.mark.parametrize(
  'change',
  [
    {'algo': 'ppo'},
    {'safety_penalty': 0.0},
    {'hidden': (32, 32)},
    {'seed': 1},
    {'task': 'turn_fixed'},
  ],
)
def test_resume_refuses_other_settings_and_leaves_the_run(trained_run, change):
  output, _ = trained_run
  files = {
    path.name: path.read_bytes()
    for path in output.iterdir()
    if path.suffix in ('.json', '.jsonl', '.zip', '.npz')
  }
  with pytest.raises(ValueError, match='--resume: .*other settings'):
    learning.train(_config(**change), output, resume=True, **QUIET)
  for name, data in files.items():
    assert (output / name).read_bytes() == data, name


@pytest.mark.slow
def test_resume_refuses_another_valve(tmp_path):
  config = _config(task='turn_fixed', steps=16, eval_every=16)
  learning.train(config, tmp_path, **QUIET)
  other = dataclasses.replace(config, task_kwargs={'valve': 'valve4'})
  with pytest.raises(ValueError, match='task_kwargs'):
    learning.train(other, tmp_path, resume=True, **QUIET)


def test_resume_without_a_run_is_refused(tmp_path):
  with pytest.raises(ValueError, match='no checkpoint'):
    learning.train(_config(), tmp_path, resume=True, **QUIET)


@pytest.mark.slow
@pytest.mark.parametrize('algo', ['sac', 'sac_sb3', 'ppo', 'trpo'])
def test_numpy_policy_equals_the_library_prediction(tmp_path, algo):
  config = _config(
    algo=algo, task='turn_fixed', steps=64, eval_every=64, safety_penalty=0
  )
  learning.train(config, tmp_path, **QUIET)
  model = agents.load(agents.get(algo), tmp_path / 'checkpoint.zip', None)
  numpy_policy = policies.load(tmp_path / 'policy.npz')
  observations = np.random.default_rng(1).normal(size=(32, 21))
  expected, _ = model.predict(
    observations.astype(np.float32), deterministic=True
  )
  np.testing.assert_allclose(
    numpy_policy.act(observations), expected, atol=1e-5
  )
  assert numpy_policy.metadata['algo'] == algo


@pytest.mark.slow
def test_on_policy_runs_say_they_round_up_to_whole_rollouts(tmp_path):
  lines = []
  history = learning.train(
    _config(algo='ppo', steps=3000, eval_every=3000, safety_penalty=0),
    tmp_path,
    log=lines.append,
  )
  assert history[-1]['env_steps'] == 4096
  assert 'whole rollouts of 2048' in lines[0] and '4096' in lines[0]


@pytest.fixture(scope='module')
def pose_demos(tmp_path_factory):
  pytest.importorskip('pyarrow', reason='needs robel_dm[data]')
  directory = tmp_path_factory.mktemp('demos')
  evaluation.evaluate(
    evaluation.EvalConfig(
      'dclaw',
      'pose_fixed',
      20,
      policy='reference',
      seed=0,
      record=str(directory),
    )
  )
  return directory


@pytest.mark.slow
def test_demonstrations_load_as_aligned_transitions(pose_demos):
  keys = learning.metadata_of(_config(task='pose_fixed'))['observation_keys']
  data = demos.load(pose_demos, 'dclaw', 'pose_fixed', tuple(keys))
  assert data.episodes == 20
  assert data.observations.shape == data.next_observations.shape
  assert data.observations.shape[1] == 27
  assert len(data.actions) == len(data.rewards) == len(data.observations)
  # Consecutive transitions chain: one's next observation is the next's.
  np.testing.assert_array_equal(
    data.next_observations[:-1][~data.terminals[:-1]][:5],
    data.observations[1:][~data.terminals[:-1]][:5],
  )
  with pytest.raises(demos.DemoError, match='not dclaw/turn_random'):
    demos.load(pose_demos, 'dclaw', 'turn_random', tuple(keys))
  with pytest.raises(demos.DemoError, match='21 asked'):
    demos.load(pose_demos, 'dclaw', 'pose_fixed', tuple(keys), episodes=21)
  # Their actions are ROBEL's map's targets, not the safe map's.
  with pytest.raises(
    demos.DemoError, match='made with action_map robel, not safe'
  ):
    demos.load(pose_demos, 'dclaw', 'pose_fixed', tuple(keys),
               task_kwargs={'action_map': 'safe'})  # fmt: skip


@pytest.mark.slow
def test_behaviour_cloning_learns_the_reference_controller(
  pose_demos, tmp_path
):
  config = _config(
    task='pose_fixed',
    algo='bc',
    steps=200,
    eval_every=100,
    eval_episodes=10,
    hidden=(64, 64),
    safety_penalty=0,
    demos=(str(pose_demos),),
  )
  history = learning.train(config, tmp_path, **QUIET)
  assert [row['epoch'] for row in history] == [0, 100, 200]
  assert history[0]['success_rate'] < 0.5
  assert history[-1]['success_rate'] >= 0.8


@pytest.mark.slow
def test_demo_augmented_sac_keeps_the_demonstrations(pose_demos, tmp_path):
  config = _config(
    task='pose_fixed',
    algo='sac_demos',
    steps=64,
    eval_every=64,
    safety_penalty=0,
    demos=(str(pose_demos),),
  )
  learning.train(config, tmp_path, **QUIET)
  buffer = pickle.loads((tmp_path / 'replay_buffer.pkl').read_bytes())
  keys = learning.metadata_of(config)['observation_keys']
  data = demos.load(pose_demos, 'dclaw', 'pose_fixed', tuple(keys))
  np.testing.assert_array_equal(buffer.actions[: len(data), 0], data.actions)
  # Room for the demonstrations and every step of the run, so none of them
  # is ever overwritten.
  assert buffer.buffer_size == len(data) + 64
  assert (buffer.pos, buffer.full) == (0, True)


def test_agents_that_learn_from_demonstrations_need_them(tmp_path):
  with pytest.raises(ValueError, match='--demos'):
    learning.train(_config(algo='bc'), tmp_path, **QUIET)
  with pytest.raises(ValueError, match='does not use --demos'):
    learning.train(_config(demos=('x',)), tmp_path, **QUIET)
  assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
  ('changes', 'message'),
  [
    ({'seed': -1}, 'seed must be >= 0'),
    ({'stop_at_success': 5.0}, 'stop_at_success is a success rate'),
    ({'stop_at_success': float('nan')}, 'stop_at_success is a success rate'),
    ({'num_envs': 2, 'from_recording': ('x',)}, 'need --num_envs=1'),
    ({'algo': 'bc', 'demos': ('x',)}, '--safety_penalty: --algo=bc fits'),
    (
      {'algo': 'bc', 'demos': ('x',), 'safety_penalty': 0.0,
       'stop_at_success': 0.8},
      '--stop_at_success: --algo=bc fits',
    ),
    ({'algo': 'sac_warm'}, '--algo=sac_warm starts from another run'),
    ({'algo': 'sac_sb3', 'safety_penalty': 0.0, 'safety_budget': 5.0},
     'needs an sbx SAC agent'),
  ],
)  # fmt: skip
def test_a_setting_training_would_ignore_or_fail_on_is_refused_unwritten(
  tmp_path, changes, message
):
  # Refused before the run folder is written: the corrected command runs.
  with pytest.raises(ValueError, match=message):
    learning.train(_config(**changes), tmp_path, **QUIET)
  assert not any(tmp_path.iterdir())


def test_every_agent_names_its_source_and_paper_kind():
  kinds = {agent.paper for agent in agents.AGENTS.values()}
  assert kinds == {'SAC', 'NPG', 'BC', 'DAPG'}
  libraries = {agents.SAC_JAX, agents.SAC_TORCH, agents.PPO_TORCH,
               agents.TRPO_TORCH, agents.IMITATION_JAX}  # fmt: skip
  for agent in agents.AGENTS.values():
    assert agent.source and agent.hidden and agent.library in libraries
  # The default agent is the numpy-acting SAC; sac_lr3e4 its predecessor.
  assert agents.AGENTS['sac'].hyperparameters['learning_rate'] == 1e-3
  assert 'learning_rate' not in agents.AGENTS['sac_lr3e4'].hyperparameters


@pytest.mark.slow
@pytest.mark.parametrize('missing', ['sbx', 'stable_baselines3', 'jax'])
def test_without_the_learn_extra_train_says_what_to_install(tmp_path, missing):
  import subprocess  # noqa: PLC0415
  import sys  # noqa: PLC0415

  output = tmp_path / 'run'
  program = (
    f'import sys; sys.modules[{missing!r}] = None; '
    f"sys.argv = ['train', '--output_dir={output}', '--steps=8']; "
    'from absl import app; from robel_dm.commands import train; '
    'train._define_flags(); app.run(train.main)'
  )
  result = subprocess.run(
    [sys.executable, '-c', program], capture_output=True, text=True
  )
  assert result.returncode == 2
  lines = [
    line for line in result.stderr.splitlines() if line.startswith('error')
  ]
  assert lines == [
    f'error: training needs the learn extra ({missing} is missing): '
    'pip install -e ".[learn]" (in the checkout)'
  ]
  assert not output.exists()


@pytest.mark.slow
@pytest.mark.parametrize(
  'flag, partner',
  [('stop_streak=3', 'stop_at_success'), ('demo_episodes=5', 'demos')],
)
def test_train_refuses_a_flag_without_the_one_it_works_with(
  tmp_path, flag, partner
):
  import subprocess  # noqa: PLC0415
  import sys  # noqa: PLC0415

  output = tmp_path / 'run'
  result = subprocess.run(
    [sys.executable, '-m', 'robel_dm.commands.train', f'--output_dir={output}',
     '--steps=8', f'--{flag}'],
    capture_output=True, text=True, timeout=120,
  )  # fmt: skip
  assert result.returncode == 2, result.stderr
  name = flag.split('=')[0]
  assert result.stderr.strip().splitlines() == [
    f'error: --{name} needs --{partner} (alone it does nothing)'
  ]
  assert not output.exists()


@pytest.mark.slow
def test_resume_refuses_a_run_built_with_other_agent_settings(tmp_path):
  config = _config(steps=16, eval_every=16)
  learning.train(config, tmp_path, **QUIET)
  saved = json.loads((tmp_path / 'config.json').read_text())
  saved['hyperparameters']['batch_size'] = 256  # An older default.
  (tmp_path / 'config.json').write_text(json.dumps(saved))
  with pytest.raises(ValueError, match='start a new run'):
    learning.train(config, tmp_path, resume=True, **QUIET)


@pytest.mark.parametrize(
  'changes, message',
  [
    ({'safety_budget': -1.0}, 'safety_budget must be >= 0'),
    ({'safety_budget': float('nan')}, 'safety_budget must be >= 0'),
    ({'safety_budget': 10.0}, 'choose one of safety_penalty'),
    (
      {'safety_budget': 10.0, 'safety_penalty': 0.0, 'algo': 'trpo'},
      '--safety_budget needs an sbx SAC agent',
    ),
    ({'init_from': '/nonexistent/run'}, 'no saved model there'),
  ],
)
def test_bad_budget_and_start_settings_are_named(changes, message):
  with pytest.raises(ValueError, match=message):
    _config(**changes).check()


@pytest.mark.slow
def test_a_warm_start_begins_where_its_source_ended(tmp_path):
  source = tmp_path / 'source'
  history = learning.train(_config(steps=152, eval_every=152), source, **QUIET)
  config = _config(init_from=str(source), steps=152, eval_every=152)
  rows = learning.train(config, tmp_path / 'warm', **QUIET)
  # The untrained evaluation is the source's last actor, on the same
  # evaluation episodes.
  assert rows[0]['env_steps'] == 0
  assert rows[0]['mean_score'] == history[-1]['mean_score']
  assert rows[0]['mean_return'] == history[-1]['mean_return']
  metadata = json.loads((tmp_path / 'warm' / 'metadata.json').read_text())
  assert metadata['init_from'] == str(source)


def test_a_warm_start_refuses_a_source_of_other_networks(tmp_path):
  source = tmp_path / 'source'
  source.mkdir()
  (source / 'checkpoint.zip').write_bytes(b'')  # Only its settings count.
  settings = _config(algo='sac').to_json()
  (source / 'config.json').write_text(json.dumps(settings))
  # DroQ's critics (dropout, layer norm) are not SAC's.
  with pytest.raises(ValueError, match='made by --algo=sac .*pass --algo=sac'):
    _config(algo='droq', init_from=str(source)).check()
  with pytest.raises(ValueError, match=r'networks \[16, 16\]'):
    _config(init_from=str(source), hidden=(32, 32)).check()
  with pytest.raises(ValueError, match='learned with action_map robel'):
    _config(init_from=str(source), task_kwargs={'action_map': 'safe'}).check()
  # The same networks with other settings: a warm start's purpose.
  _config(algo='sac_warm', init_from=str(source)).check()
  _config(init_from=str(source / 'checkpoint.zip')).check()


@pytest.mark.slow
def test_a_safety_budget_learns_a_price_per_violation(tmp_path):
  config = _config(safety_penalty=0.0, safety_budget=0.0)
  learning.train(config, tmp_path / 'safe', **QUIET)
  from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: PLC0415

  env = DummyVecEnv([lambda: learning.make_env(config, 0)])
  model = agents.load(config.agent, tmp_path / 'safe' / 'checkpoint.zip', env)
  # Pose's random early actions break the velocity limit: over budget.
  assert model.safety.budget == 0.0
  assert model.safety.multiplier > 0.0
  saved = json.loads((tmp_path / 'safe' / 'config.json').read_text())
  assert saved['safety_budget'] == 0.0


@pytest.mark.parametrize('name', sorted(agents.AGENTS))
def test_every_agent_is_documented(name):
  root = pathlib.Path(__file__).resolve().parents[1]
  table = (root / 'docs/baselines.md').read_text()
  assert f'| `{name}` ' in table  # A row of the agents' table.
  assert f'| `{name}` ' in agents.__doc__
