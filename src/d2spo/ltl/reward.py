"""The reward as trained: TLGRL's Eq. (8) from automaton progress, plus potential-based shaping.

``step_reward`` is the one function the environment calls each step. The shaping's distances are
measured by the environment (they need the layout: ``envs.geodesic``, ``envs.state_fields``) and
combined here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from d2spo.fields import check_choice, check_fields
from d2spo.ltl.automaton import UNREACHABLE, AutomatonArrays

PER_STATE = "geodesic-per-state"
"""The shaping metric that reads one distance field per automaton state (``envs.state_fields``)."""
SHAPING_METRICS = ("geodesic", "euclidean", PER_STATE)
"""Values of ``RewardConfig.shaping_metric``."""


@dataclass(frozen=True)
class RewardConfig:
    """Constants of Eq. (8) and of the cases the paper leaves open."""

    c_n: float = 0.01
    """Per-step penalty when the automaton state does not change (q' = q)."""
    c_p: float = 2.0
    """Bonus when q' is strictly closer to acceptance than q (q' in Prog(q))."""
    r_goal: float = 10.0
    """Reward when q' is accepting (task completed)."""
    c_regress: float = 2.0
    """Penalty when q' changes but is not closer to acceptance (not in the paper; see docs)."""
    r_reject: float = 10.0
    """Penalty when q' is rejecting: the task can no longer be completed (not in the paper)."""
    c_collision: float = 10.0
    """Penalty on a collision (not in the paper; see docs/ltl.md). It must clearly exceed
    c_n / (1 - gamma) = 1, what staying at q forever costs, or crashing is a way out of the -c_n
    stream of Eq. (8); with 1, TD3 learnt to drive into walls. The default equals r_reject."""
    shaping: float = 10.0
    """Weight of the potential-based distance shaping added to Eq. (8) (not in the paper; 0 turns
    it off). The potential is minus the distance still to travel, in arena diagonals: automaton
    distance plus the distance to the nearest area that makes progress over the diagonal. 10 makes
    one metre toward the next area worth ~1.4 on the arena of 5 m x 5 m (1 was too weak for TD3
    to find even a single area; docs/ltl.md)."""
    shaping_metric: str = PER_STATE
    """'geodesic-per-state' (the default): one field per automaton state, the path to the areas whose
    entry makes progress that also goes round the areas whose entry would reject the task or undo
    progress (``envs.state_fields``); it also checks, before training, that the task can be done on
    the layout. 'geodesic': the shortest obstacle-free path to the nearest area that makes progress,
    straight through the others (``envs.geodesic``; it may lead through an area whose entry rejects
    the task); 'euclidean': straight line, which leads into obstacles lying on the line."""
    shaping_clearance: float | None = 0.3
    """With a geodesic metric: path nodes closer than this to an obstacle or a wall cost more per
    metre (``envs.geodesic.BLOCKED_COST`` with 'geodesic', ``shaping_clearance_cost`` with
    'geodesic-per-state'), so the shortest path keeps this clearance where it can. The default 0.3 m equals the barrier's safe distance (``cbf.d``), so the path
    stays in the CBF's safe set; None: the robot radius (0.15 m), i.e. only paths the robot cannot
    take are penalised, and the path may run inside the barrier's margin, where D²SPO's policy
    crawls (docs/ltl.md)."""
    shaping_clearance_cost: float = 2.0
    """With 'geodesic-per-state': a path step costs its length times this where a node is closer
    than the clearance to an obstacle or a wall (coming closer than the clearance to a forbidden area
    costs ``envs.geodesic.BLOCKED_COST`` times the approach). 2, as in the generalist's
    field bank (``envs.layout_bank``):
    a 0.75-0.8 m opening lies almost wholly in the clearance band, and a steep cost there makes the
    field jump sideways at the opening's mouth, where the policy dithers (docs/ltl.md)."""
    shaping_collide_cost: float = 100.0
    """With 'geodesic-per-state': the multiplier where a node is closer than the robot's radius to an
    obstacle or a wall (the robot would collide there), so no path cuts a wall."""
    shaping_neighbours: int = 8
    """With 'geodesic-per-state': the grid moves of the fields' shortest paths. 8 (the default): the
    8-neighbourhood, whose path lengths exceed the straight segment by up to 8.2% (at 22.5 deg), so
    every monotone path inside a 45-degree cone is as short as the straight one; 16: knight moves
    (1, 2) too, at most 2.7% over, a field closer to the Euclidean path length (``envs.state_fields``)."""
    shaping_gamma: float = 1.0
    """Discount in the shaping term gamma * Phi(s') - Phi(s). 1 (not the learner's 0.99): with
    gamma < 1 standing still far from the goal earns (1 - gamma) |Phi| > c_n per step."""
    mode: str = "progress"
    """'progress' = Eq. (8); 'sparse' = r_goal on completion only (the RL-phi ablation)."""

    def __post_init__(self) -> None:
        # magnitudes: each constant enters Eq. (8) with its sign written there
        check_fields(self, "reward", nullable=("shaping_clearance",),
                     non_negative=("c_n", "c_p", "r_goal", "c_regress", "r_reject", "c_collision", "shaping",
                                   "shaping_clearance"),
                     at_least_one=("shaping_clearance_cost", "shaping_collide_cost"),
                     fraction=("shaping_gamma",))
        check_choice(self, "mode", ("progress", "sparse"), "reward")
        check_choice(self, "shaping_metric", SHAPING_METRICS, "reward")
        check_choice(self, "shaping_neighbours", (8, 16), "reward")

    @property
    def shaped(self) -> bool:
        """Whether ``step_reward`` adds the shaping term (progress mode and shaping != 0)."""
        return self.mode == "progress" and self.shaping != 0.0

    def clearance(self, robot_radius: float) -> float:
        """The shaping path's clearance (m): ``shaping_clearance``, or the robot radius if None."""
        return robot_radius if self.shaping_clearance is None else self.shaping_clearance

    def field_costs(self, robot_radius: float) -> dict[str, float]:
        """``envs.state_fields.state_fields``'s keyword arguments for this reward and robot."""
        return dict(clearance=self.clearance(robot_radius), robot_radius=robot_radius,
                    clearance_cost=self.shaping_clearance_cost, collide_cost=self.shaping_collide_cost,
                    neighbours=self.shaping_neighbours)


def progress_reward(
    aut: AutomatonArrays, q: jnp.ndarray, q_next: jnp.ndarray, cfg: RewardConfig, collided: jnp.ndarray | bool = False,
    visit: jnp.ndarray | None = None
) -> jnp.ndarray:
    """Eq. (8): -c_n if q' = q; +c_p if q' is closer to acceptance; r_goal if q' is accepting.

    Entering a rejecting state costs r_reject; any other change of state that does not get closer
    costs c_regress. Accepting and rejecting states are absorbing, so reaching them is counted once
    (the step on which q' first becomes accepting/rejecting). ``visit`` (a Büchi task's step, else
    None: ``labelling.accepting_visit``): an accepting visit gets r_goal too, and the distance
    jumping back up after it costs nothing.
    """
    newly_accepting = aut.accepting[q_next] & ~aut.accepting[q]
    if visit is not None:
        newly_accepting = newly_accepting | visit
    crash = jnp.where(collided, -cfg.c_collision, 0.0)
    if cfg.mode == "sparse":
        return (jnp.where(newly_accepting, cfg.r_goal, 0.0) + crash).astype(jnp.float32)
    same = q_next == q
    closer = aut.distance[q_next] < aut.distance[q]
    newly_rejecting = aut.rejecting[q_next] & ~aut.rejecting[q]
    r = jnp.where(same, -cfg.c_n, jnp.where(closer, cfg.c_p, -cfg.c_regress))
    r = jnp.where(newly_accepting, cfg.r_goal, r)
    r = jnp.where(newly_rejecting, -cfg.r_reject, r)
    return (r + crash).astype(jnp.float32)


def progress_areas(aut: AutomatonArrays, area_bits) -> jnp.ndarray:
    """bool [Q, N]: entering area i alone from state q gets strictly closer to acceptance, or is a
    Büchi task's accepting visit (after which the distance restarts). Computed on the host (integer
    gathers and comparisons, exact): it is built once per env, and eagerly on the device each of its
    operations compiled a program."""
    area_bits = np.asarray(area_bits)
    delta, distance = np.asarray(aut.delta), np.asarray(aut.distance)
    nxt = delta[:, area_bits]  # [Q, N]
    closer = distance[nxt] < distance[:, None]
    if aut.visit is not None:
        closer = closer | np.asarray(aut.visit)[:, area_bits]
    return jnp.asarray(closer & (area_bits[None, :] != 0))


def distance_to_progress(advance: jnp.ndarray, q: jnp.ndarray, center_dist: jnp.ndarray, radius: jnp.ndarray
                         ) -> jnp.ndarray:
    """The robot's distance to the nearest area whose entry makes progress from q (0 if none).

    ``advance`` is ``progress_areas``; ``center_dist`` [N] the robot's distance to each area's
    centre (straight or along free space); the distance to an area is that minus its (labelling)
    radius, at least 0.
    """
    gap = jnp.maximum(center_dist - radius, 0.0)  # [N]
    near = jnp.min(jnp.where(advance[q], gap, jnp.inf))
    return jnp.where(jnp.isfinite(near), near, 0.0)


def potential(aut: AutomatonArrays, q: jnp.ndarray, near: jnp.ndarray, scale: jnp.ndarray | float) -> jnp.ndarray:
    """Phi(s, q) = -(distance(q) * scale + near) / scale, 0 at acceptance: minus the distance still
    to travel, in units of ``scale`` (the arena's diagonal, so one automaton step is worth about
    any travel). ``near`` is the robot's distance to what makes progress from q
    (``distance_to_progress``, or the field of state q with ``shaping_metric="geodesic-per-state"``)."""
    finite = aut.distance < UNREACHABLE
    worst = jnp.max(jnp.where(finite, aut.distance, 0)) + 1  # a dead automaton counts one step further
    steps = jnp.where(finite[q], aut.distance[q], worst).astype(jnp.float32)
    return jnp.where(aut.accepting[q], 0.0, -(steps * scale + near) / scale)


def shaping_term(phi: jnp.ndarray, phi_next: jnp.ndarray, cfg: RewardConfig) -> jnp.ndarray:
    """Potential-based shaping (Ng et al., 1999): w * (gamma * Phi(s') - Phi(s))."""
    return cfg.shaping * (cfg.shaping_gamma * phi_next - phi)


ShapingDistances = Callable[[], tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]]
"""Measures, when called, (near, near_next, scale): the robot's distance to what makes progress
from q before the step and from q' after it, and the arena's diagonal."""


def step_reward(aut: AutomatonArrays, q: jnp.ndarray, q_next: jnp.ndarray, collided: jnp.ndarray,
                cfg: RewardConfig, distances: ShapingDistances, visit: jnp.ndarray | None = None) -> jnp.ndarray:
    """The reward of one step as trained: Eq. (8) (``progress_reward``, with the collision
    penalty), plus ``shaping_term`` of the potentials before and after the step when ``cfg.shaped``.

    ``distances`` is called only then; the environment measures them with ``cfg.shaping_metric``.
    ``visit``: whether a Büchi task's step is an accepting visit (None for a monitor); the potential
    after a visit counts as 0, as at acceptance, and the next step starts from the state's own.
    """
    reward = progress_reward(aut, q, q_next, cfg, collided, visit)
    if not cfg.shaped:
        return reward
    near, near_next, scale = distances()
    phi = potential(aut, q, near, scale)
    phi_next = potential(aut, q_next, near_next, scale)
    if visit is not None:
        phi_next = jnp.where(visit, 0.0, phi_next)
    return reward + shaping_term(phi, phi_next, cfg)
