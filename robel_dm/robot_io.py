"""What a task may ask of the robot it runs on, beyond the physics state.

A task reads joint angles and velocities from the physics, whether it is
simulated or fed by motors. A few things exist only on some robots: the
motors' measured currents, a guide motor that shows or sets a goal, a
motion tracker's targets, and the motion that brings a real robot to an
episode's initial state. `RobotIO` is that contract. `SimulatedRobotIO`
answers it for simulation (nothing measured, nothing to move); the hardware
layer provides its own implementation and hands it to the task
(`RobelTask.use_robot_io`). A task asks the contract; it never inspects the
physics.
"""

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class RobotIO(Protocol):
  """Robot-specific inputs and outputs a task may use."""

  @property
  def motor_currents(self) -> np.ndarray | None:
    """Measured currents of the robot's joint motors, mA, in action order:
    an array updated in place every control step; None if not measured."""

  def realize_initial_state(self) -> None:
    """Moves the robot to the joint state the task has just set in the
    physics (inside the episode's initialization), then reads it back."""

  def show_goal(self, goal: float) -> None:
    """Shows the task's goal angle (rad) on a goal display, if any."""

  def goal_from_person(self) -> float | None:
    """The goal angle a person sets by hand (rad), or None if nobody can."""

  def tracked_target(self) -> np.ndarray | None:
    """A tracked target's floor position (x, y), m, or None if untracked."""

  def tracked_heading(self) -> np.ndarray | None:
    """A tracked heading marker's floor position (x, y), m, or None."""


class SimulatedRobotIO:
  """`RobotIO` of a simulated robot: nothing is measured beyond the physics,
  there is no goal display or tracker, and the physics state is the robot's
  state."""

  motor_currents = None

  def realize_initial_state(self) -> None:
    pass

  def show_goal(self, goal: float) -> None:
    del goal

  def goal_from_person(self) -> None:
    return None

  def tracked_target(self) -> None:
    return None

  def tracked_heading(self) -> None:
    return None


SIMULATION = SimulatedRobotIO()
