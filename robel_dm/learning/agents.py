"""The learning agents `train --algo=` offers, and what each one is.

ROBEL's paper compares four kinds of agent; each kind has an agent here,
from a named library (or, for behaviour cloning, this package):

| name        | kind            | source                                   |
|-------------|-----------------|------------------------------------------|
| `sac`       | off-policy      | sbx-rl 0.28 `SAC` (SB3's API on JAX)     |
| `sac_lr3e4` | off-policy      | the same, learning rate 3e-4             |
| `sac_sb3`   | off-policy      | Stable-Baselines3 2.9.2 `SAC` (torch)    |
| `ppo`       | on-policy       | Stable-Baselines3 2.9.2 `PPO` (torch)    |
| `trpo`      | on-policy (NPG) | sb3-contrib 2.9.2 `TRPO` (torch)         |
| `bc`        | imitation       | `robel_dm.learning.imitation` (JAX)      |
| `sac_demos` | demo-augmented  | sbx `SAC` with the demonstrations kept   |
|             |                 | in its replay buffer                     |
| `droq`      | off-policy      | sbx `SAC`, DroQ critics (dropout, layer  |
|             |                 | norm), 10 updates per env step           |
| `sac_safe`  | off-policy      | `sac` under a safety budget, through the |
|             |                 | safe action map (in the baseline plan)   |
| `sac_warm`  | off-policy      | `sac` from the Random variant's networks |
| `sac_tight` | off-policy      | `sac_safe`'s budget through ROBEL's map, |
|             |                 | from the same task's `sac` networks      |
| `sac_asymmetric` | off-policy | `sac`, critics observing the privileged  |
|             |                 | state (RandomDynamics)                   |
| `sac_privileged` | off-policy | `sac`, actor and critics observing it    |
| `sac_privileged_dynamics` | off-policy | the same, seeing the dynamics |
|             |                 | only (not the D'Kitty's terrain)         |
| `sac_curriculum` | off-policy | `sac`, randomization grown by degrees    |

`sac` is the default: the fastest way to ROBEL's success found on two CPU
cores (benchmarks/training_speed.py measures it against `sac_sb3`, SB3's
SAC with its defaults). Every agent learns on one CPU thread.
"""

import contextlib
import dataclasses
import importlib.util
import os
import pathlib
from typing import Any

import numpy as np

from robel_dm import policies
from robel_dm.learning import actor

# One CPU thread per run (XLA reads this when JAX starts): two runs on two
# cores beat one run on both.
_XLA_ONE_THREAD = (
  '--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1'
)
SAC_JAX, SAC_TORCH, PPO_TORCH, TRPO_TORCH, IMITATION_JAX = (
  'sbx_sac',
  'sb3_sac',
  'sb3_ppo',
  'sb3_contrib_trpo',
  'imitation',
)
# What a privileged agent's networks observe beyond a robot's observation
# (the task's `privileged` observation: randomized dynamics, terrain).
PRIVILEGED_ACTOR, PRIVILEGED_CRITIC = 'actor', 'critic'
OFF_POLICY, ON_POLICY, IMITATION, DEMO_AUGMENTED = (
  'off-policy',
  'on-policy',
  'imitation',
  'demo-augmented',
)


@dataclasses.dataclass(frozen=True)
class Agent:
  """What `train --algo=<name>` runs.

  Attributes:
    name: the `--algo` value.
    kind: OFF_POLICY, ON_POLICY, IMITATION or DEMO_AUGMENTED.
    paper: the column of ROBEL's paper it stands for (SAC, NPG, BC, DAPG).
    source: the library and class (or module) that implements it.
    hidden: hidden layer sizes of its networks.
    hyperparameters: the library's constructor arguments robel_dm sets.
    replay: whether it keeps a replay buffer (saved beside checkpoints).
    needs_demos: whether it learns from demonstrations (`--demos`).
    library: the class that implements it: `SAC_JAX`
      (`robel_dm.learning.sac.SAC`), `SAC_TORCH`, `PPO_TORCH`, `TRPO_TORCH`
      or `IMITATION_JAX`.
    network: the library policy's arguments beside the layer sizes (sbx
      SAC: `dropout_rate` and `layer_norm` of its critics).
    safety_budget: the safety violations per episode it learns to stay
      under (`train --safety_budget`'s default); None: no budget.
    starts_from: in the baseline table, the variant whose run of the same
      seed (by `sac`) it starts from ('random': a RandomDynamics task's
      Random variant; 'same': the same task); None: from scratch.
    privileged: on a RandomDynamics task, which networks also observe the
      task's privileged observation (what only a simulation knows):
      PRIVILEGED_ACTOR, actor and critics (a ceiling for any policy a
      robot can run); PRIVILEGED_CRITIC, the critics only (an asymmetric
      actor-critic: the actor sees what a robot gives); None: neither.
    privileged_view: what the privileged observation holds for it (the
      task option `privileged`): True, the randomized dynamics and the
      terrain under the D'Kitty; 'dynamics', the randomized dynamics only.
    curriculum: on a RandomDynamics task, the share of the run's budget
      over which its training episodes' randomization grows from the
      nominal robot to the task's ranges
      (`RobelTask.set_randomization_scale`); None: the task's ranges from
      the start.
  """

  name: str
  kind: str
  paper: str
  source: str
  hidden: tuple[int, ...]
  hyperparameters: dict[str, Any]
  replay: bool = False
  needs_demos: bool = False
  library: str = ''
  network: dict[str, Any] = dataclasses.field(default_factory=dict)
  safety_budget: float | None = None
  starts_from: str | None = None
  privileged: str | None = None
  privileged_view: bool | str = True
  curriculum: float | None = None


# SAC's usual settings (256 x 256, learning rate 3e-4, one update per env
# step) with the 8 updates of every 8 env steps in one jitted call,
# learning from 500 steps on, and batches of 128, which halve the cost of an
# update: the default agent until the learning rate below was measured.
_SAC_LR3E4 = {
  'train_freq': 8,
  'gradient_steps': 8,
  'learning_starts': 500,
  'batch_size': 128,
}
# The default: the same with learning rate 1e-3, which reached 80% success
# in fewer env steps on Pose, Stand and Turn (benchmarks/agent_settings.py;
# docs/baselines_history.md, "Choosing the default agent").
_SAC = {**_SAC_LR3E4, 'learning_rate': 1e-3}
# Ten updates per env step, made stable by regularized critics (DroQ:
# dropout and layer normalization): fewer env steps to 80% success (robot
# time), ten times the updates (CPU time); benchmarks/agent_settings.py.
_DROQ = {**_SAC, 'gradient_steps': 80}
_DROQ_CRITICS = {'dropout_rate': 0.01, 'layer_norm': True}

_PRIVILEGED = Agent(
  'sac_privileged',
  OFF_POLICY,
  'SAC',
  'sbx-rl 0.28.0 SAC (JAX), learning rate 1e-3, actor and critics '
  "observing the episode's randomized dynamics and terrain (simulation "
  'only: a ceiling)',
  (256, 256),
  _SAC,
  replay=True,
  library=SAC_JAX,
  privileged=PRIVILEGED_ACTOR,
)

AGENTS: dict[str, Agent] = {
  agent.name: agent
  for agent in (
    Agent(
      'sac',
      OFF_POLICY,
      'SAC',
      'sbx-rl 0.28.0 SAC (JAX), learning rate 1e-3',
      (256, 256),
      _SAC,
      replay=True,
      library=SAC_JAX,
    ),
    Agent(
      'sac_lr3e4',
      OFF_POLICY,
      'SAC',
      'sbx-rl 0.28.0 SAC (JAX), learning rate 3e-4 (the default agent '
      'before 2026-11-25)',
      (256, 256),
      _SAC_LR3E4,
      replay=True,
      library=SAC_JAX,
    ),
    Agent(
      'sac_sb3',
      OFF_POLICY,
      'SAC',
      'stable-baselines3 2.9.2 SAC (torch), its defaults',
      (256, 256),
      {},
      replay=True,
      library=SAC_TORCH,
    ),
    Agent(
      'ppo',
      ON_POLICY,
      'NPG',
      'stable-baselines3 2.9.2 PPO (torch), its defaults',
      (64, 64),
      {},
      library=PPO_TORCH,
    ),
    Agent(
      'trpo',
      ON_POLICY,
      'NPG',
      'sb3-contrib 2.9.2 TRPO (torch), its defaults',
      (64, 64),
      {},
      library=TRPO_TORCH,
    ),
    Agent(
      'bc',
      IMITATION,
      'BC',
      'robel_dm.learning.imitation (JAX): mean squared error on the '
      'demonstrated actions',
      (256, 256),
      {'batch_size': 256, 'learning_rate': 1e-3},
      needs_demos=True,
      library=IMITATION_JAX,
    ),
    Agent(
      'droq',
      OFF_POLICY,
      'SAC',
      'sbx-rl 0.28.0 SAC (JAX), learning rate 1e-3, critics with dropout '
      '0.01 and layer normalization (DroQ), 10 updates per env step',
      (256, 256),
      _DROQ,
      replay=True,
      library=SAC_JAX,
      network=_DROQ_CRITICS,
    ),
    Agent(
      'sac_safe',
      OFF_POLICY,
      'SAC',
      'sbx-rl 0.28.0 SAC (JAX), learning rate 1e-3, under a budget of 10 '
      'safety violations per episode (a learned Lagrange multiplier)',
      (256, 256),
      _SAC,
      replay=True,
      library=SAC_JAX,
      safety_budget=10.0,
    ),
    Agent(
      'sac_warm',
      OFF_POLICY,
      'SAC',
      'sbx-rl 0.28.0 SAC (JAX), learning rate 1e-3, starting from the '
      "networks of the Random variant's sac run of the same seed",
      (256, 256),
      _SAC,
      replay=True,
      library=SAC_JAX,
      starts_from='random',
    ),
    Agent(
      'sac_tight',
      OFF_POLICY,
      'SAC',
      'sbx-rl 0.28.0 SAC (JAX), learning rate 1e-3, under a budget of 10 '
      'safety violations per episode, starting from the networks of the '
      "same task's sac run of the same seed",
      (256, 256),
      _SAC,
      replay=True,
      library=SAC_JAX,
      safety_budget=10.0,
      starts_from='same',
    ),
    _PRIVILEGED,
    dataclasses.replace(
      _PRIVILEGED,
      name='sac_privileged_dynamics',
      source='sbx-rl 0.28.0 SAC (JAX), learning rate 1e-3, actor and '
      "critics observing the episode's randomized dynamics, not the terrain "
      '(simulation only: a ceiling for a policy that does not know them)',
      # Networks that see the terrain learned nothing on Orient
      # RandomDynamics: this one asks what knowing the physics is worth.
      privileged_view='dynamics',
    ),
    Agent(
      'sac_asymmetric',
      OFF_POLICY,
      'SAC',
      'sbx-rl 0.28.0 SAC (JAX), learning rate 1e-3, critics observing the '
      "episode's randomized dynamics, the actor not",
      (256, 256),
      _SAC,
      replay=True,
      library=SAC_JAX,
      privileged=PRIVILEGED_CRITIC,
      # Not the terrain: new in every episode, it lets a critic tell
      # episodes apart (Stand RandomDynamics: docs/baselines.md).
      privileged_view='dynamics',
    ),
    Agent(
      'sac_curriculum',
      OFF_POLICY,
      'SAC',
      'sbx-rl 0.28.0 SAC (JAX), learning rate 1e-3, its training '
      "episodes' randomization growing from the nominal robot to the "
      "task's ranges over the first half of the budget",
      (256, 256),
      _SAC,
      replay=True,
      library=SAC_JAX,
      curriculum=0.5,
    ),
    Agent(
      'sac_demos',
      DEMO_AUGMENTED,
      'DAPG',
      'sbx-rl 0.28.0 SAC (JAX), learning rate 3e-4, the demonstrations '
      'kept in its replay buffer for the whole run',
      (256, 256),
      _SAC_LR3E4,
      replay=True,
      needs_demos=True,
      library=SAC_JAX,
    ),
  )
}
DEFAULT = 'sac'
# On a robot env steps are the budget, not CPU: fewer of them to 80% on
# Pose, Turn and Stand (docs/robot_training.md, Sample-efficient learning).
ROBOT_DEFAULT = 'droq'


def updates_per_step(agent: Agent) -> float:
  """The gradient updates an off-policy agent makes per env step."""
  hyper = agent.hyperparameters
  return hyper.get('gradient_steps', 1) / hyper.get('train_freq', 1)


def get(name: str) -> Agent:
  """The agent called `name`.

  Raises:
    ValueError: naming the agents there are.
  """
  if name not in AGENTS:
    raise ValueError(f'algo must be one of {sorted(AGENTS)}, got {name!r}')
  return AGENTS[name]


def _default_jax_cache() -> pathlib.Path:
  """`$XDG_CACHE_HOME/robel_dm/jax`, else under ~/.cache: where JAX keeps
  compiled updates between runs unless `JAX_COMPILATION_CACHE_DIR` says."""
  cache = os.environ.get('XDG_CACHE_HOME') or pathlib.Path.home() / '.cache'
  return pathlib.Path(cache) / 'robel_dm' / 'jax'


def single_thread() -> None:
  """Pins torch and (if not started yet) JAX to one CPU thread, and has
  JAX reuse its compilations from earlier runs (if not started yet)."""
  os.environ.setdefault('XLA_FLAGS', _XLA_ONE_THREAD)
  os.environ.setdefault('JAX_PLATFORMS', 'cpu')  # No probing for a TPU.
  # A run compiles some 70 small functions, each under JAX's default 1 s
  # threshold for caching but seconds in all: cache every one.
  os.environ.setdefault('JAX_COMPILATION_CACHE_DIR', str(_default_jax_cache()))
  os.environ.setdefault('JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS', '0')
  _start_jax_on_one_core()
  import torch  # noqa: PLC0415 (heavy; only when learning)

  torch.set_num_threads(1)


def _start_jax_on_one_core() -> None:
  """Starts JAX's CPU client (if not started yet) while this thread may
  use one core, then gives every thread of the process its cores back.

  XLA sizes its thread pool by the cores the process may use when the
  client starts, whatever `XLA_FLAGS` say; with a worker per core an
  update spreads over both cores of a 2-core machine at 1.3-1.6 times
  the CPU time (benchmarks/update_cost.py), taken from the run on the
  other core.
  """
  if not hasattr(os, 'sched_setaffinity'):  # Linux only.
    return
  try:
    import jax  # noqa: PLC0415 (heavy; only when learning)
  except ImportError:  # A torch-only install.
    return
  cores = os.sched_getaffinity(0)
  os.sched_setaffinity(0, {min(cores)})
  try:
    jax.devices()  # Starts the client; a no-op once it is started.
  finally:
    # Threads started meanwhile inherited the one core.
    for thread in pathlib.Path('/proc/self/task').iterdir():
      with contextlib.suppress(OSError):  # Ended meanwhile.
        os.sched_setaffinity(int(thread.name), cores)


def shared_random_streams() -> dict[str, Any]:
  """The process-wide random streams the libraries draw from (torch's,
  numpy's and Python's: SB3's agents sample actions and minibatches from
  them), which loading a saved model seeds again from the run's seed."""
  import random  # noqa: PLC0415

  import torch  # noqa: PLC0415

  return {
    'torch': torch.get_rng_state(),
    'numpy': np.random.get_state(),
    'python': random.getstate(),
  }


def set_shared_random_streams(streams: dict[str, Any]) -> None:
  """Puts the process-wide random streams where `shared_random_streams`
  found them."""
  import random  # noqa: PLC0415

  import torch  # noqa: PLC0415

  torch.set_rng_state(streams['torch'])
  np.random.set_state(streams['numpy'])
  random.setstate(streams['python'])


def check_installed(agent: Agent) -> None:
  """Imports what `agent` needs.

  Raises:
    ImportError: naming the missing package (the `learn` extra has all).
  """
  if agent.kind == IMITATION:
    import jax  # noqa: F401, PLC0415
    import optax  # noqa: F401, PLC0415
  else:
    _library_class(agent.library)


# The packages each library needs (the first missing one is named).
_PACKAGES = {
  SAC_JAX: ('jax', 'flax', 'optax', 'sbx', 'stable_baselines3', 'torch'),
  SAC_TORCH: ('stable_baselines3', 'torch'),
  PPO_TORCH: ('stable_baselines3', 'torch'),
  TRPO_TORCH: ('sb3_contrib', 'stable_baselines3', 'torch'),
  IMITATION_JAX: ('jax', 'optax'),
}


def check_available(agent: Agent) -> None:
  """Checks that the packages `agent` needs are installed without
  importing them (seconds for JAX and torch): for a process that leaves
  the learning to another, as a robot's actor does.

  Raises:
    ModuleNotFoundError: naming the first missing package.
  """
  for name in _PACKAGES[agent.library]:
    try:
      found = importlib.util.find_spec(name) is not None
    except ValueError:  # Imported once and then set to None in sys.modules.
      found = False
    if not found:
      raise ModuleNotFoundError(f'No module named {name!r}', name=name)


def _library_class(library: str):
  single_thread()
  if library == SAC_JAX:
    from robel_dm.learning import sac  # noqa: PLC0415 (imports JAX)

    return sac.SAC
  if library == TRPO_TORCH:
    import sb3_contrib  # noqa: PLC0415

    return sb3_contrib.TRPO
  import stable_baselines3  # noqa: PLC0415

  return {SAC_TORCH: stable_baselines3.SAC, PPO_TORCH: stable_baselines3.PPO}[
    library
  ]


def build(
  agent: Agent, env, seed: int, hidden: tuple[int, ...], buffer_size: int
):
  """A new model of `agent` learning on the vectorized `env` (whose
  observation ends with the privileged one if `agent.privileged`)."""
  cls = _library_class(agent.library)
  kwargs = dict(agent.hyperparameters)
  if agent.replay:
    kwargs['buffer_size'] = max(buffer_size, 1)
  policy_kwargs = {'net_arch': list(hidden), **agent.network}
  if agent.privileged == PRIVILEGED_CRITIC:
    privileged = env.get_attr('privileged_size')[0]
    policy_kwargs['actor_class'] = cls.prefix_actor(
      env.observation_space.shape[0] - privileged
    )
  return cls(
    'MlpPolicy',
    env,
    seed=seed,
    policy_kwargs=policy_kwargs,
    verbose=0,
    **kwargs,
  )


def load(agent: Agent, path, env):
  """A model saved by `model.save(path)`."""
  return _library_class(agent.library).load(str(path), env=env, device='cpu')


def warm_start(agent: Agent, source, env, seed: int, buffer_size: int):
  """A new model of `agent` starting from another run's networks.

  The actor, the critics and the entropy coefficient come from the saved
  model `source`; its counters, random streams and replay buffer do not:
  the new run counts from 0, draws from `seed` and stores only its own
  transitions.

  Raises:
    ValueError: naming the difference, if `source` was made for other
      observations or actions than `env`'s.
  """
  model = load(agent, source, env)
  model.start_over(seed, buffer_size)
  return model


def sac_actor_layers(model) -> list[tuple[np.ndarray, np.ndarray]]:
  """An sbx SAC actor's dense layers as (weight (out, in), bias) arrays:
  the hidden layers, then the mean, then the log-std."""
  return actor.layers_of(model.policy.actor_state.params)


def numpy_policy(model, metadata: dict[str, Any]) -> policies.NumpyPolicy:
  """The deterministic actor of a trained model, for numpy."""
  policy = model.policy
  if hasattr(policy, 'actor_state'):  # sbx SAC: tanh of the mean.
    layers = sac_actor_layers(model)[:-1]  # Without the log-std.
    return policies.NumpyPolicy(
      [weight for weight, _ in layers],
      [bias for _, bias in layers],
      'relu',
      'tanh',
      metadata,
    )
  from torch import nn  # noqa: PLC0415

  if hasattr(policy, 'actor'):  # SB3 SAC: tanh of the mean.
    layers = [*policy.actor.latent_pi, policy.actor.mu]
    output = 'tanh'
  else:  # PPO and TRPO: the mean, clipped to the action bounds.
    layers = [*policy.mlp_extractor.policy_net, policy.action_net]
    output = 'clip'
  linear = [layer for layer in layers if isinstance(layer, nn.Linear)]
  activations = {
    type(layer).__name__.lower()
    for layer in layers
    if not isinstance(layer, nn.Linear)
  }
  if len(activations) > 1 or not activations <= {'relu', 'tanh'}:
    raise ValueError(f'unsupported activations {activations}')
  return policies.NumpyPolicy(
    [layer.weight.detach().cpu().numpy() for layer in linear],
    [layer.bias.detach().cpu().numpy() for layer in linear],
    activations.pop() if activations else 'relu',
    output,
    metadata,
  )
