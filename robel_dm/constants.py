"""Constants shared across robel_dm's layers: ROBEL's timing, noise, and
the device name of the in-process virtual servo bus.

ROBEL's numbers: docs/robel_reference.md section 1.
"""

# Physics timestep of every ROBEL scene, seconds (400 Hz).
PHYSICS_TIMESTEP = 0.0025

# Control timesteps, seconds: frame skip 20 for D'Claw Pose, 40 elsewhere.
CONTROL_TIMESTEP_FAST = 0.05
CONTROL_TIMESTEP = 0.1

# ROBEL's sim observation noise in RandomDynamics variants: a fraction of each
# joint's range width (noise = fraction * U(-0.5, 0.5) * width).
OBSERVATION_NOISE_FRACTION = 0.05

# `device_path` of the in-process virtual servo bus (see suite.load).
VIRTUAL_DEVICE = 'virtual'

# How a missing extra is installed (robel_dm installs from its checkout):
# INSTALL_EXTRA.format('hardware').
INSTALL_EXTRA = 'pip install -e ".[{}]" (in the checkout)'
