"""Building blocks shared by every algorithm: networks, GAE, losses, the Lagrange
multiplier and the Lagrangian cost-critic shell.

Import the modules themselves; those with colliding function names (``lagrange.update``,
``normalize.update``) read best through the module: ``from d2spo.algos.common import lagrange``.
"""
