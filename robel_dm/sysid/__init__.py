"""System identification: fit the simulated robot to the real one.

1. Record excitation episodes on the robot (or the virtual bus):

     robel-sysid excite --domain=dclaw \
       --device_path=/dev/ttyUSB0 --record=runs/excite

2. Fit the joint dynamics and control delay to them (the report warns, one
   line each, of values the recordings do not pin down):

     robel-sysid fit runs/excite --domain=dclaw \
       --output=dclaw_calibration.json

3. Simulate the calibrated robot:

     suite.load('dclaw', 'pose_fixed', dynamics='dclaw_calibration.json')

In Python: `robel_dm.sysid.excite` (the sequences; `excite.run` drives an
environment through one) and `robel_dm.sysid.fit` (`fit.load_trajectories`,
`fit.fit`); `robel_dm.sysid.report` formats a fit as text. The command is
`robel_dm.commands.sysid`. See docs/sysid.md.
"""
