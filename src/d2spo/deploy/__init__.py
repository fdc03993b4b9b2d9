"""Run a policy that ``d2spo export`` wrote, on a robot or in a simulator: numpy only, no JAX.

>>> from d2spo.deploy import Policy
>>> policy = Policy.load("exported/phi1")        # manifest.json + weights.npz
>>> task = policy.task_tracker()
>>> q = task.reset(x, y)                          # the automaton reads the start's areas
>>> u = policy.act(ranges, (x, y, theta), q)      # [2] in [-1, 1]; filter=True/False overrides the default
>>> v, omega = policy.command(u)                  # what the wheels are told
>>> q = task.update(x, y)                         # after the step, from the pose reached

``import d2spo.deploy`` imports neither JAX nor flax (``d2spo/__init__.py`` imports none either),
so a robot needs only numpy (and onnxruntime for ``Policy.load(..., backend="onnxruntime")``).
docs/deploy.md describes the artefact and the calls.
"""

from d2spo.deploy.manifest import FORMAT, FORMAT_VERSION
from d2spo.deploy.policy import Policy
from d2spo.deploy.task import Automaton, TaskTracker

__all__ = ["FORMAT", "FORMAT_VERSION", "Automaton", "Policy", "TaskTracker"]
