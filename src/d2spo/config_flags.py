"""``TrainConfig`` as the ``d2spo train`` command line reads it: the flags of one learner
(``flags_for``), the learner and the ``--config`` file a command line names before tyro parses it
(``algo_named``, ``config_file_named``), and the plain ``TrainConfig`` of what tyro returns (``plain``)."""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import field
from pathlib import Path
from typing import Annotated

import tyro

from d2spo.algos import all_config_sections, config_sections, known_algos
from d2spo.config import TrainConfig, config_file


def flags_for(algo: str) -> type:
    """``TrainConfig`` as the command line shows it for ``algo``: the config sections other learners
    read are hidden (``tyro.conf.Suppress``), so ``d2spo train --algo A --help`` lists the flags that
    apply to A, and a flag A would ignore is refused. An unknown ``algo`` shows every section
    (``TrainConfig`` then refuses the algorithm). ``plain`` turns what it parses into a ``TrainConfig``."""
    keep = set(config_sections(algo)) if algo in known_algos() else all_config_sections()
    hints = typing.get_type_hints(TrainConfig, include_extras=True)
    hidden = [(f.name, Annotated[hints[f.name], tyro.conf.Suppress], field(default_factory=f.default_factory))
              for f in dataclasses.fields(TrainConfig) if f.name in all_config_sections() - keep]
    return dataclasses.make_dataclass("TrainConfig", hidden, bases=(TrainConfig,), frozen=True)


def _flag_value(args: list[str], flag: str) -> str | None:
    """The last value ``--flag V`` or ``--flag=V`` gives on a command line, None if none does."""
    given = [b for a, b in zip(args, args[1:]) if a == flag] + [a[len(flag) + 1:] for a in args
                                                                  if a.startswith(flag + "=")]
    return given[-1] if given else None


def algo_named(args: list[str], base: TrainConfig | None = None) -> str:
    """The learner a ``d2spo train`` command line names with ``--algo`` (default: ``base``'s, the
    ``--config`` file's, or ``TrainConfig``'s)."""
    return _flag_value(args, "--algo") or (base or TrainConfig).algo


def config_file_named(args: list[str]) -> TrainConfig | None:
    """The config of the file ``d2spo train --config FILE`` names (``config_file``), None without one."""
    path = _flag_value(args, "--config") if args[:1] == ["train"] else None
    return None if path is None else config_file(Path(path))


def plain(cfg: TrainConfig) -> TrainConfig:
    """A ``TrainConfig`` with the values of ``cfg`` (an instance of a ``flags_for`` class), and the
    names of the step counts and minibatch ``cfg`` filled itself (``filled_cbf_fields``)."""
    out = TrainConfig(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(TrainConfig)})
    object.__setattr__(out, "filled_cbf_fields", getattr(cfg, "filled_cbf_fields", ()))
    return out
