"""Learning on robel_dm tasks: agents, training runs, demonstrations,
behaviour cloning and learning curves (the `learn` extra)."""
