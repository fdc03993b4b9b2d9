"""The runs each of the paper's tables and figures needs (``d2spo reproduce``'s targets).

A target (table2, table3, fig2 … fig5) is a list of ``RunSpec``: learner, task, layout, preset,
seed, episodes, policy snapshots. A run lives in ``OUT/runs/NAME``, an ordinary run directory.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from d2spo.config import TrainConfig
from d2spo.envs import EnvConfig
from d2spo.errors import UserError

TARGETS = ("table2", "table3", "fig2", "fig3", "fig4", "fig5")
METHODS = ("cpo", "ppo-lag", "td3-lag", "sac-lag", "rcrl", "d2spo")
"""The rows of Tables II and III, in the paper's order."""
TABLE_SETTING = {"table2": ("phi1", "paper"), "table3": ("relaxed", "relaxed")}
PHYSICAL = ("physical-1", "physical-2", "physical-3", "physical-4")
FIG4_EPISODES = 2000
"""Fig. 4 learns the CBF of a TurtleBot on each physical layout; the paper gives no episode count.
The barrier is learnt from the first episodes on, so 2000 (a tenth of the protocol) by default."""


@dataclass(frozen=True)
class RunSpec:
    """One training run of a target."""

    algo: str
    task: str
    layout: str
    seed: int
    episodes: int
    preset: str | None = None
    snapshots: tuple[int, ...] = ()

    @property
    def name(self) -> str:
        preset = f"-{self.preset}" if self.preset else ""
        snaps = "-snapshots" if self.snapshots else ""  # not interchangeable with the same run without them
        return f"{self.algo}-{self.task}-{self.layout}{preset}{snaps}-s{self.seed}"

    def config(self):
        env = EnvConfig(layout=self.layout, preset=self.preset or "default")
        return TrainConfig(algo=self.algo, task=self.task, episodes=self.episodes, seed=self.seed, env=env,
                           snapshots=self.snapshots).check()


def scaled(episodes: int, full: int, n: int) -> int:
    """``n`` of the paper's ``full``-episode protocol, scaled to a run of ``episodes`` (at least 1)."""
    return max(1, round(n * episodes / full))


def fig5_snapshots(episodes: int) -> tuple[int, ...]:
    """The paper shows the robot after 2000, 10000 and 20000 of 20000 episodes."""
    return tuple(sorted({scaled(episodes, 20_000, n) for n in (2_000, 10_000, 20_000)}))


def runs_for(target: str, seeds: int, episodes: int, methods: Iterable[str] = METHODS) -> list[RunSpec]:
    """The runs a target needs (fig2 reuses the runs of table2 and table3)."""
    seeds_ = range(seeds)
    if target in TABLE_SETTING:
        task, layout = TABLE_SETTING[target]
        return [RunSpec(m, task, layout, s, episodes) for m in methods for s in seeds_]
    if target == "fig2":
        return runs_for("table2", seeds, episodes, methods) + runs_for("table3", seeds, episodes, methods)
    if target == "fig3":
        a = [RunSpec(m, t, "open", s, episodes) for m in ("td3", "tlgrl") for t in ("phi1", "phi2") for s in seeds_]
        b = [RunSpec(m, t, "paper", s, episodes) for m in ("sl", "d2spo") for t in ("phi1", "phi2") for s in seeds_]
        return a + b
    if target == "fig4":
        n = scaled(episodes, 20_000, FIG4_EPISODES)
        return [RunSpec("d2spo", "phi1", lay, 0, n, preset="turtlebot") for lay in PHYSICAL]
    if target == "fig5":
        return [RunSpec("d2spo", "phi1", "paper", 0, episodes, snapshots=fig5_snapshots(episodes))]
    raise UserError(f"unknown target {target!r}; choose one of {', '.join(TARGETS)} or all")


def expand(targets: Iterable[str]) -> list[str]:
    out: list[str] = []
    for t in targets:
        for x in (TARGETS if t == "all" else (t,)):
            if x not in TARGETS:
                raise UserError(f"unknown target {x!r}; choose one of {', '.join(TARGETS)} or all")
            if x not in out:
                out.append(x)
    return out


def run_dir(out: Path, spec: RunSpec) -> Path:
    return Path(out) / "runs" / spec.name


def is_finished(out: Path, spec: RunSpec) -> bool:
    return (run_dir(out, spec) / "summary.json").is_file()
