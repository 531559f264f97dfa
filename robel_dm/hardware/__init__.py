"""Real-robot support (Dynamixel bus and hardware physics); see issue #4."""
