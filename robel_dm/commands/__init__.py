"""The command lines, on top of everything else: one module per command.

Each module is the command's flags and a thin call into its library; each
runs as its installed script (`robel-evaluate`) or as
`python -m robel_dm.commands.evaluate`. No other module imports them (the
import contracts in `pyproject.toml` check it).

  evaluate     robel-evaluate: evaluate a policy on tasks (ROBEL's metrics)
  train        robel-train: train an agent, in simulation or on a robot
  plot         robel-plot: plot evaluation results side by side
  view         robel-view: open the interactive viewer on a task
  virtual_bus  robel-virtual-bus: serve a robot's motors on a virtual bus
  scan         robel-scan: diagnose the motors on a Dynamixel bus
  sysid        robel-sysid: excite a robot and fit its simulated dynamics
  recording    robel-recording: list a recording, export it to LeRobot
  convert      robel-convert: a Stable-Baselines3 model as a policy.npz
  baselines    robel-baselines: train and report the baseline table
  zoo          robel-zoo: the held-out robots' transfer table
"""
