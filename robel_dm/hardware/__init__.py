"""Real robots: Dynamixel client, robot configurations, the hardware physics
shim, resets, torso tracking, diagnostics and a virtual servo bus.

The suite imports `shutdown` (the standard library only) up front, so that
the exit-signal handlers are installed from the main thread; the rest is
imported only when a task is loaded with a `device_path`, so that the
simulation works without the optional `dynamixel-sdk`.
"""
