"""D'Claw Screw: turn the valve continuously at a goal velocity (2.2)."""

from dm_control.composer.variation import distributions
import numpy as np

from robel_dm import constants, randomization, registry
from robel_dm.tasks import dclaw_turn

_EPISODE_STEPS = 80  # 8 s at 10 Hz.
# Success: mean |angle error| over the episode below this, rad (ROBEL's
# success_threshold for Screw; its paper quotes 0.1).
_SUCCESS_THRESHOLD = 0.2
_FIXED_GOAL_VELOCITY = 0.5  # rad/s.
_RANDOM_INITIAL_ANGLE = distributions.Uniform(-np.pi, np.pi)
_RANDOM_GOAL_VELOCITY = distributions.Uniform(-0.75, 0.75)


def _screw(**kwargs) -> dclaw_turn.TurnTask:
  # The goal starts at the valve's initial angle (goal_angle=None).
  return dclaw_turn.TurnTask(
    goal_angle=None,
    episode_steps=_EPISODE_STEPS,
    success_threshold=_SUCCESS_THRESHOLD,
    success_on=dclaw_turn.SUCCESS_ON_MEAN_ERROR,
    **kwargs,
  )


@registry.DCLAW.add(registry.FIXED)
def screw_fixed(**kwargs) -> dclaw_turn.TurnTask:
  """Turn from 0 at +0.5 rad/s."""
  return _screw(initial_angle=0.0, goal_velocity=_FIXED_GOAL_VELOCITY, **kwargs)


@registry.DCLAW.add(registry.RANDOM)
def screw_random(**kwargs) -> dclaw_turn.TurnTask:
  """Random initial angle and goal velocity."""
  return _screw(
    initial_angle=_RANDOM_INITIAL_ANGLE,
    goal_velocity=_RANDOM_GOAL_VELOCITY,
    **kwargs,
  )


@registry.DCLAW.add(registry.RANDOM_DYNAMICS)
def screw_random_dynamics(**kwargs) -> dclaw_turn.TurnTask:
  """screw_random with randomized dynamics and observation noise."""
  return screw_random(
    dynamics=randomization.DCLAW_VALVE,
    observation_noise=constants.OBSERVATION_NOISE_FRACTION,
    **kwargs,
  )
