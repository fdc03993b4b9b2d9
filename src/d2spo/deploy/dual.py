"""Forward-mode derivatives over numpy: what the runtime filter needs of ∇_u c(u), without JAX.

A ``Dual`` holds a value ``v`` (float32 array) and its tangents ``d`` (``v.shape + (n,)``: the
derivative of every entry along n input directions). The functions below take Duals or plain
arrays alike, so the sensor model and the networks are written once (``deploy.geometry``,
``deploy.nets``) and give values alone, or values and derivatives. Each rule follows JAX's own,
ties included, so the filter's gradient is the one ``jax.grad`` takes in ``safety.filter``:
``minimum``/``maximum`` split a tie's tangent in half (``lax``'s balanced rule), ``min_last``
averages it over the tied entries (``reduce_min``), ``abs`` takes the tangent's sign from x ≥ 0.
"""

from __future__ import annotations

import numpy as np

F32 = np.float32


class Dual:
    """A value and its tangents along n directions (the last axis of ``d``)."""

    __slots__ = ("v", "d")
    __array_ufunc__ = None  # numpy defers to the reflected operators below

    def __init__(self, v, d):
        self.v = v
        self.d = d

    def __add__(self, o):
        if isinstance(o, Dual):
            return Dual(self.v + o.v, self.d + o.d)
        v = self.v + o
        return Dual(v, _bcast(self.d, np.shape(v)))

    __radd__ = __add__

    def __neg__(self):
        return Dual(-self.v, -self.d)

    def __sub__(self, o):
        return self + (-o)

    def __rsub__(self, o):
        return (-self) + o

    def __mul__(self, o):
        if isinstance(o, Dual):
            return Dual(self.v * o.v, self.d * _t(o.v) + _t(self.v) * o.d)
        o = np.asarray(o, F32) if not isinstance(o, np.ndarray) else o
        return Dual(self.v * o, self.d * _t(o))

    __rmul__ = __mul__

    def __truediv__(self, o):
        if isinstance(o, Dual):
            v = self.v / o.v
            return Dual(v, (self.d - _t(v) * o.d) / _t(o.v))
        return Dual(self.v / o, self.d / _t(np.asarray(o, F32)))

    def __rtruediv__(self, o):  # o / self
        v = o / self.v
        return Dual(v, -self.d * _t(v / self.v))

    def __getitem__(self, i):
        """Index the value's leading axes (no Ellipsis: the tangent axis is last)."""
        return Dual(self.v[i], self.d[i])


def _t(a):
    """a with a trailing axis for the tangents."""
    return np.asarray(a)[..., None]


def _bcast(d, shape):
    return np.broadcast_to(d, tuple(shape) + d.shape[-1:])


def value(a):
    return a.v if isinstance(a, Dual) else a


def seed(v: np.ndarray) -> Dual:
    """``v`` [n] as the n input directions: its tangents are the identity."""
    v = np.asarray(v, F32)
    return Dual(v, np.eye(v.shape[-1], dtype=F32))


def _tangent(parts, v):
    """The sum of the Duals' weighted tangents among ``parts`` ((operand, weight) pairs), shaped v.shape + (n,)."""
    d = sum(a.d * _t(w) for a, w in parts if isinstance(a, Dual))
    shape = np.shape(v) + d.shape[-1:]
    return d if d.shape == shape else np.broadcast_to(d, shape)


def _choose(a, b, v):
    """Tangent of min/max(a, b) = v: a's where a alone gives v, b's where b alone does, half each on a tie."""
    if not isinstance(a, Dual) and not isinstance(b, Dual):
        return v
    ea, eb = value(a) == v, value(b) == v
    tie = ea & eb
    wa = np.where(tie, F32(0.5), ea.astype(F32))
    wb = np.where(tie, F32(0.5), eb.astype(F32))
    return Dual(v, _tangent([(a, wa), (b, wb)], v))


def minimum(a, b):
    return _choose(a, b, np.minimum(value(a), value(b)))


def maximum(a, b):
    return _choose(a, b, np.maximum(value(a), value(b)))


def clip(a, lo, hi):
    """``jnp.clip``: the maximum with lo, then the minimum with hi."""
    return minimum(maximum(a, lo), hi)


def where(cond, a, b):
    v = np.where(cond, value(a), value(b))
    if not isinstance(a, Dual) and not isinstance(b, Dual):
        return v
    return Dual(v, _tangent([(a, cond), (b, ~np.asarray(cond))], v))


def sqrt(a):
    if not isinstance(a, Dual):
        return np.sqrt(a)
    v = np.sqrt(a.v)
    return Dual(v, a.d / _t(F32(2.0) * v))


def abs(a):
    if not isinstance(a, Dual):
        return np.abs(a)
    return Dual(np.abs(a.v), np.where(_t(a.v >= 0), a.d, -a.d))


def tanh(a):
    if not isinstance(a, Dual):
        return np.tanh(a)
    v = np.tanh(a.v)
    return Dual(v, a.d * _t((F32(1.0) + v) * (F32(1.0) - v)))


def cos(a):
    if not isinstance(a, Dual):
        return np.cos(a)
    return Dual(np.cos(a.v), -a.d * _t(np.sin(a.v)))


def sin(a):
    if not isinstance(a, Dual):
        return np.sin(a)
    return Dual(np.sin(a.v), a.d * _t(np.cos(a.v)))


def min_last(a, keepdims: bool = False):
    """Minimum over the last axis; a tie shares the tangent equally (JAX's ``reduce_min``)."""
    if not isinstance(a, Dual):
        return np.min(a, axis=-1, keepdims=keepdims)
    v = np.min(a.v, axis=-1, keepdims=True)
    at = (a.v == v).astype(F32)
    d = np.sum(a.d * _t(at), axis=-2, keepdims=True) / _t(np.sum(at, axis=-1, keepdims=True))
    return Dual(v, d) if keepdims else Dual(v[..., 0], d[..., 0, :])


def min_first(a):
    """Minimum over the first axis (the obstacles), a tie sharing the tangent equally. The env takes
    it as a chain of pairwise minima (which halves a tie's tangent at each link): the two differ only
    where two obstacles give one ray exactly the same range."""
    if not isinstance(a, Dual):
        return np.min(a, axis=0)
    v = np.min(a.v, axis=0)
    at = (a.v == v).astype(F32)
    return Dual(v, np.sum(a.d * _t(at), axis=0) / _t(np.sum(at, axis=0)))


def concat(parts: list, axis: int = -1):
    """Concatenate along the last axis (0 for 1-D values)."""
    if not any(isinstance(p, Dual) for p in parts):
        return np.concatenate(parts, axis=axis)
    n = next(p.d.shape[-1] for p in parts if isinstance(p, Dual))
    vs = [value(p) for p in parts]
    ds = [p.d if isinstance(p, Dual) else np.zeros(np.shape(p) + (n,), F32) for p in parts]
    return Dual(np.concatenate(vs, axis=axis), np.concatenate(ds, axis=axis - 1 if axis < 0 else axis))


def stack(parts: list):
    """Stack scalars (or equal shapes) along a new last axis."""
    if not any(isinstance(p, Dual) for p in parts):
        return np.stack(parts, axis=-1)
    n = next(p.d.shape[-1] for p in parts if isinstance(p, Dual))
    ds = [p.d if isinstance(p, Dual) else np.zeros(np.shape(p) + (n,), F32) for p in parts]
    return Dual(np.stack([value(p) for p in parts], axis=-1), np.stack(ds, axis=-2))


def dense(a, kernel: np.ndarray, bias: np.ndarray):
    """x @ kernel + bias (flax ``Dense``), for x of any leading shape."""
    if not isinstance(a, Dual):
        return a @ kernel + bias
    return Dual(a.v @ kernel + bias, np.einsum("...in,io->...on", a.d, kernel))
