"""Task registries, one per domain, and the tags that classify variants."""

from dm_control.utils import containers

# Variant tags (ROBEL's Fixed / Random / RandomDynamics).
FIXED = 'fixed'
RANDOM = 'random'
RANDOM_DYNAMICS = 'random_dynamics'

DCLAW = containers.TaggedTasks()
DKITTY = containers.TaggedTasks()

DOMAINS = {'dclaw': DCLAW, 'dkitty': DKITTY}
