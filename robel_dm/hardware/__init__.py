"""Real robots: Dynamixel client, robot configurations, the hardware physics
shim, resets, torso tracking, diagnostics and a virtual servo bus.

Imported only when a task is loaded with a `device_path`, so that the
simulation works without the optional `dynamixel-sdk`.
"""
