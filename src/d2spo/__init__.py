"""d2spo: data-driven safe policy optimization (D²SPO) with LTL tasks, in JAX."""

from d2spo import _xla

_xla.apply()  # before JAX starts its backend: see d2spo/_xla.py

__version__ = "0.1.0"
