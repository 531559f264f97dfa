"""The D'Kitty's torso pose and targets from a motion-capture system.

`tracker` (TorsoTracker and the tracked-pose types), `natnet` (an OptiTrack
NatNet stream client) and `spec` (the `--tracker` specification).
"""
