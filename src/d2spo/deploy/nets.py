"""The exported networks in numpy: dense layers with an activation each, as the manifest lists them.

``Mlp.__call__`` runs one on a vector or a batch; it also takes a ``dual.Dual`` (the filter
differentiates h and the nominal model in u). ``network_input`` is ``safety.cbf.network_input``:
what h and π_Ω read of x = b(z, O_s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from d2spo.deploy import dual as ad
from d2spo.deploy.dual import F32


def _sigmoid(a):
    return F32(1.0) / (F32(1.0) + np.exp(-a))


ACTIVATIONS = {
    "linear": lambda a: a,
    "relu": lambda a: np.maximum(a, F32(0.0)),
    "tanh": ad.tanh,
    "sigmoid": _sigmoid,
}
"""The activations an exported layer may name (tanh also on Duals)."""


@dataclass(frozen=True)
class Layer:
    kernel: np.ndarray
    """float32 [in, out]."""
    bias: np.ndarray
    """float32 [out]."""
    activation: str
    """A key of ``ACTIVATIONS``."""


@dataclass(frozen=True)
class Mlp:
    layers: tuple[Layer, ...]

    def __call__(self, x):
        for layer in self.layers:
            x = ACTIVATIONS[layer.activation](ad.dense(x, layer.kernel, layer.bias))
        return x


def network_input(x, H):
    """x/H with min(x)/H appended (``safety.cbf.network_input``)."""
    x = x / H
    return ad.concat([x, ad.min_last(x, keepdims=True)])


@dataclass(frozen=True)
class SafetyPolicy:
    """π_Ω(x, u_rl) = u_rl + β ⊙ (a − u_rl) (``safety.joint_policy.SafetyPolicy``)."""

    hidden: Mlp
    """The tanh trunk on (network_input(x), u_rl)."""
    beta: Layer
    """β's head (sigmoid)."""
    a: Layer
    """The safe action's head (tanh)."""
    H: np.float32

    def __call__(self, x: np.ndarray, u_rl: np.ndarray) -> np.ndarray:
        h = self.hidden(np.concatenate([network_input(x, self.H), u_rl], axis=-1))
        beta = Mlp((self.beta,))(h)
        a = Mlp((self.a,))(h)
        return u_rl + beta * (a - u_rl)
