"""Robots and props: each entity owns its MJCF model and its observables."""
