"""Task registries, one per domain, and the tags that classify variants."""

from dm_control.utils import containers

from robel_dm import robots

# Variant tags (ROBEL's Fixed / Random / RandomDynamics).
FIXED = 'fixed'
RANDOM = 'random'
RANDOM_DYNAMICS = 'random_dynamics'

# One registry per robot of `robots.ROBOTS`.
DOMAINS = {name: containers.TaggedTasks() for name in robots.ROBOTS}
DCLAW = DOMAINS[robots.DCLAW.name]
DKITTY = DOMAINS[robots.DKITTY.name]
