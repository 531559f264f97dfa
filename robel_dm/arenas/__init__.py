"""Arenas: the scenes that robots and props are attached to."""
