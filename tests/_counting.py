"""Counting calls: how often a run computes something (a task's distances, a generalist's build)."""

from __future__ import annotations


def count_calls(monkeypatch, targets: dict[str, tuple[object, str]]) -> dict[str, int]:
    """Wrap each ``getattr(owner, attr)`` of ``targets`` (name -> (owner, attr)) so that every call
    adds one to the returned dict's entry ``name``; the wrappers go when the test ends. What this
    process built and compiled before is forgotten (``d2spo.memo``), so the calls are counted."""
    from d2spo import memo

    memo.clear()
    calls = dict.fromkeys(targets, 0)
    for name, (owner, attr) in targets.items():
        def wrapper(*args, _f=getattr(owner, attr), _name=name, **kwargs):
            calls[_name] += 1
            return _f(*args, **kwargs)

        monkeypatch.setattr(owner, attr, wrapper)
    return calls
