"""D²SPO, Algorithm 1: TLGRL (TD3 on Eq. (8)) with a data-driven CBF and the executed policy π_Ω.

Per vectorised step (lines 6–16 of Algorithm 1):

1. π_rl proposes u_rl = π(z; φ) + exploration noise (uniform during warm-up);
2. the executed policy returns u = π_Ω(x, u_rl), x = b(z, O_s) the sensed features (line 8);
   optionally the runtime filter corrects u under the learned barrier and nominal model;
3. every env steps with u; (z, u, r, z') goes into TD3's replay buffer (line 9);
4. (z, z', O_s) goes into T, P_exp and X_L (line 11, ``safety.datasets.update_datasets``);
5. TD3 updates critics and, delayed, actor and targets (lines 12–15). With ``pipeline`` (an
   option, off by default) these updates run one chunk behind, in a second program beside the
   rollout (``rollout``, ``td3_batches``, ``td3_chunk``; d2spo/pipelined.py).

Every ``update_every`` steps, (Θ, Ω) take ``cbf.updates_per_iter`` steps on Eq. (9) and f_n is
refitted on T (line 17). Before the first env step, h, π_Ω and f_n are pre-trained on synthetic
sensed data (``safety.joint_policy.cautious_start``), so exploration is safe from episode one.

The learner never calls the env's dynamics: f_n is fitted to observed (s, u, s') only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
from flax import serialization, struct

from d2spo.algos.base import ChunkLog, episode_log, params_finite
from d2spo.algos.d2spo_pipeline import PipelinedChunks
from d2spo.algos.offpolicy import explore_and_store
from d2spo.algos.one_layout import OneLayout
from d2spo.algos.td3 import (
    TD3Agent,
    TD3Carry,
    TD3Config,
    TD3Learner,
    explore,
    learn_from_buffer,
    no_updates,
)
from d2spo.envs import sensors
from d2spo.envs.sensors import Sensed
from d2spo.errors import ConfigError
from d2spo.fields import check_fields
from d2spo.ltl.anneal import AnnealConfig
from d2spo.replay import ReplayBuffer
from d2spo.safety import datasets as sd
from d2spo.safety.cbf import CBFConfig, check_geometry
from d2spo.safety.filter import safety_filter
from d2spo.safety.joint_policy import (
    SafetyState,
    cautious_start,
    init_safety_state,
    make_nets,
    safe_action,
    update,
)
from d2spo.safety.nominal import unicycle_prior


@dataclass(frozen=True)
class D2SPOConfig:
    """How D²SPO schedules its safety learning (the networks and losses are in CBFConfig)."""

    update_every: int = 25
    """Vectorised steps between two UPDATE(Ω, Θ)."""
    pretrain: bool = True
    """Cautious start: pre-train h, π_Ω and f_n."""
    kinematic_prior: bool = True
    """Start f_n from the kinematic unicycle."""
    runtime_filter: bool = False
    """Project π_Ω's action onto the barrier condition."""
    actor_through_safety: bool | None = None
    """Actor loss via π_Ω; None: on, off for --generalist."""
    proposal_weight: float = 1.0
    """Weight of ||π(z) - π_Ω(x, π(z))||² in the actor loss."""
    synthetic_box_half: tuple[float, float] = (0.15, 0.45)
    """Half-sizes (m) of the cautious start's boxes."""
    pipeline: bool = False
    """Experimental: TD3's updates one chunk behind, beside the rollout (faster; collides more)."""

    def __post_init__(self) -> None:
        check_fields(self, "d2spo", nullable=("actor_through_safety",), count=("update_every",),
                     non_negative=("proposal_weight",),
                     flag=("pretrain", "kinematic_prior", "runtime_filter", "actor_through_safety", "pipeline"))
        lo_hi = self.synthetic_box_half
        if not (isinstance(lo_hi, tuple) and len(lo_hi) == 2 and all(isinstance(v, (int, float)) for v in lo_hi)
                and 0 < lo_hi[0] <= lo_hi[1] < math.inf):
            raise ConfigError("d2spo.synthetic_box_half", f"must be two sizes 0 < lo <= hi, got {lo_hi!r}")


@struct.dataclass
class D2SPOCarry:
    td3: TD3Carry
    """TD3's part: key, env states, observations, the agent, its replay buffer and the counters."""
    safety: SafetyState
    data: sd.SafetyData

    @property
    def agent(self) -> TD3Agent:
        return self.td3.agent

    @property
    def env_state(self) -> Any:
        return self.td3.env_state

    @property
    def obs(self) -> jax.Array:
        return self.td3.obs

    @property
    def buffer(self) -> ReplayBuffer:
        return self.td3.buffer

    @property
    def steps(self) -> jax.Array:
        return self.td3.steps

    @property
    def episodes(self) -> jax.Array:
        return self.td3.episodes


# A checkpoint holds the carry as one flat dict (flax msgpack), in the order of the fields the carry
# had before it held a TD3Carry, so that checkpoints stay byte for byte what they were and still load.
_STATE_ORDER = ("key", "env_state", "obs", "agent", "buffer", "safety", "data", "steps", "episodes")


def _carry_state_dict(c: D2SPOCarry) -> dict:
    flat = {**serialization.to_state_dict(c.td3), "safety": serialization.to_state_dict(c.safety),
            "data": serialization.to_state_dict(c.data)}
    return {k: flat[k] for k in _STATE_ORDER}


def _carry_from_state_dict(c: D2SPOCarry, state: dict) -> D2SPOCarry:
    if set(state) != set(_STATE_ORDER):
        raise ValueError(f"a D2SPOCarry state holds {sorted(_STATE_ORDER)}, not {sorted(state)}")
    td3 = serialization.from_state_dict(c.td3, {k: v for k, v in state.items() if k not in ("safety", "data")})
    return D2SPOCarry(td3, serialization.from_state_dict(c.safety, state["safety"], name="safety"),
                      serialization.from_state_dict(c.data, state["data"], name="data"))


serialization.register_serialization_state(D2SPOCarry, _carry_state_dict, _carry_from_state_dict, override=True)


class D2SPOLearner(PipelinedChunks, TD3Learner):
    """``--algo d2spo`` (and ``--algo sl``: the same without the progress reward). ``PipelinedChunks``
    gives the ``rollout``, ``td3_batches`` and ``td3_chunk`` of ``--d2spo.pipeline``."""

    def __init__(self, env, params, cfg: TD3Config, cbf: CBFConfig, anneal: AnnealConfig, num_envs: int,
                 chunk_steps: int, total_episodes: int, d2spo: D2SPOConfig | None = None, layouts=OneLayout):
        """``layouts(env, params, d2spo)`` builds where the learner reads its layout: ``OneLayout``, or
        ``algos.generalist.LayoutBank`` for a bank of them."""
        super().__init__(env, params, cfg, anneal, num_envs, chunk_steps, total_episodes)
        self.cbf_cfg = cbf
        self.d2 = d2spo or D2SPOConfig()
        econf = env.config
        check_geometry(cbf, float(econf.robot_radius), float(econf.sensing_radius))
        self.H = float(econf.sensing_radius)
        self.dt = float(econf.dt)
        self.safety_nets = make_nets(cbf, self.H)
        self.n_obstacles = int(params.geom.n_obstacles)
        self.n_features = env.n_rays + 1
        self.layouts = layouts(env, params, self.d2)
        self._safety_metrics = None  # shapes of UPDATE(Ω, Θ)'s metrics, traced once (``_iteration``)

    @property
    def pipelined(self) -> bool:
        """Whether the run loop runs ``rollout`` and ``td3_chunk`` side by side (``train.learner_program``,
        d2spo/pipelined.py) instead of ``chunk``: ``d2spo.pipeline``."""
        return bool(self.d2.pipeline)

    @property
    def params_as_argument(self) -> bool:
        """Whether the run loop passes the env params to ``init`` and ``chunk`` as an argument
        (``train.learner_program``): the generalist's field bank is too large for constants."""
        return self.layouts.params_as_argument

    # -- the layout, read through ``self.layouts`` from self.params, so a learner acting on other params follows them
    @property
    def arena_lo(self) -> jax.Array:
        return self.layouts.arena(self.params)[0]

    @property
    def arena_hi(self) -> jax.Array:
        return self.layouts.arena(self.params)[1]

    # -- the sensor model x = b(z, O_s), envs/sensors.py, with this learner's arena, K and H ------
    def features(self, pose: jax.Array, ctx: Sensed, unroll: bool | None = None, for_grad: bool = False) -> jax.Array:
        """x = ``sensors.cbf_input(pose, ctx, ...)``: the ``features_fn`` the safety code is given
        (``unroll`` and ``for_grad``: the lidar's, ``sensors.lidar``)."""
        return sensors.cbf_input(pose, ctx, self.arena_lo, self.arena_hi, self.env.n_rays, self.H, unroll, for_grad)

    def features_for_grad(self, pose: jax.Array, ctx: Sensed) -> jax.Array:
        """``features`` where they are differentiated in the pose: Eq. (9)'s T_e in UPDATE(Ω, Θ), the
        cautious start (its synthetic data too), the runtime filter, and UPDATE(D)'s Newton steps onto
        the unsafe ring (``safety.datasets.synthesize_unsafe``). Each ray's first obstacle is found
        on values held constant and only its range is differentiated (``sensors.lidar``'s
        ``for_grad``): the same values, and the same gradients but on ties between obstacles
        (tests/test_env_geometry.py). The minimum's gradient ran backwards through every obstacle's
        range: this took a phi1 chunk from 1.09 to 1.01 ms per vectorised step (bench/RESULTS.md,
        "2026-12-04, afternoon"). Before it, from 2026-11-29, the minimum was one reduction here, not
        an unrolled chain per obstacle, which halved the generalist's compile time."""
        return self.features(pose, ctx, for_grad=True)

    def sensed(self, mask: jax.Array) -> Sensed:
        """O_s: this layout's obstacles with the sensed ``mask`` [..., M]."""
        return sensors.sensed_obstacles(self.params.geom, mask)

    def context(self, info: dict) -> Sensed:
        """O_s of a step, from the env's ``info`` (the sensed obstacles)."""
        return self.layouts.context(self.params, info)

    def filter_context(self, env_state) -> Sensed | None:
        """The obstacles the runtime filter keeps clear of in ``env_state`` (batched or not); None:
        all of this layout's (``execute``'s default)."""
        return self.layouts.filter_context(self.params, env_state)

    def synthetic_sample(self, key: jax.Array):
        """A hypothetical pose among random boxes (the cautious start's data, not the layout)."""
        return self.layouts.synthetic_sample(self.params, key)

    def x_of_obs(self, obs: jax.Array) -> jax.Array:
        """x of an observation: what π_Ω reads when acting."""
        return self.layouts.x_of_obs(self.params, obs)

    # -- init ----------------------------------------------------------------------------
    @property
    def long_init(self) -> bool:
        """Whether ``init`` runs long (the cautious start's pre-training): train.learner_program
        compiles it with ``_xla.long_running_options()``."""
        return bool(self.d2.pretrain)

    def init(self, key: jax.Array) -> D2SPOCarry:
        return self._init(key, self.d2.pretrain)

    def init_template(self, key: jax.Array) -> D2SPOCarry:
        """``init`` without the cautious start's pre-training, which changes values, not shapes: what
        ``jax.eval_shape`` needs for a carry's template (``run.carry_template``) at a fraction of the
        tracing (the pre-training's loops are most of ``init``'s program)."""
        return self._init(key, False)

    def _init(self, key: jax.Array, pretrain: bool) -> D2SPOCarry:
        base = super().init(key)
        k_s, k_pre, k_data = jax.random.split(jax.random.fold_in(key, 7), 3)
        safety = init_safety_state(k_s, self.safety_nets, self.cbf_cfg, self.n_features, self.env.action_size)
        if pretrain:
            pre = sd.synthetic_pretrain_data(k_data, self.features_for_grad, self.synthetic_sample,
                                             self.cbf_cfg.pretrain_samples, cfg=self.cbf_cfg)
            prior = None
            if self.d2.kinematic_prior:
                env_cfg = self.env.config
                prior = unicycle_prior(float(env_cfg.v_max), float(env_cfg.omega_max), None if env_cfg.reverse else 0.0)
            safety, _ = cautious_start(k_pre, safety, pre, nets=self.safety_nets, cfg=self.cbf_cfg,
                                       features_fn=self.features_for_grad, dt=self.dt, prior=prior,
                                       action_dim=self.env.action_size)
        example = sd.Transition(
            pose=jnp.zeros((3,)), next_pose=jnp.zeros((3,)), context=self.sensed(jnp.zeros((self.n_obstacles,), bool)),
            obs=jnp.zeros((self.env.observation_size,)), action=jnp.zeros((self.env.action_size,)),
            u_rl=jnp.zeros((self.env.action_size,)))
        data = sd.init_safety_data(self.cbf_cfg, example, self.n_features)
        if pretrain:
            data = sd.seed_unsafe(data, pre)  # X_L has the synthetic ring samples from the first update
        return D2SPOCarry(base, safety, data)

    # -- the executed policy -------------------------------------------------------------
    def execute(self, safety: SafetyState, obs: jax.Array, u_rl: jax.Array, pose: jax.Array,
                ctx: Sensed | None = None) -> jax.Array:
        """π_Ω's action, then the runtime filter's (when on) with the obstacles ``ctx`` (default: all
        of this layout's, ``filter_context``)."""
        u = safe_action(self.safety_nets, safety, self.x_of_obs(obs), u_rl)
        if self.d2.runtime_filter:
            if ctx is None:
                ctx = self.sensed(jnp.ones(u.shape[:-1] + (self.n_obstacles,), bool))

            def one(p, c, u0):
                return safety_filter(self.safety_nets, safety.cbf, safety.nominal, p, c, u0, cfg=self.cbf_cfg,
                                     features_fn=self.features_for_grad, dt=self.dt).action

            u = jax.vmap(one)(pose, ctx, u) if u.ndim == 2 else one(pose, ctx, u)
        return u

    # -- one vectorised step -------------------------------------------------------------
    def _step(self, c: D2SPOCarry, learn: bool = True):
        """One vectorised step without UPDATE(Ω, Θ): (carry, log, the step's key for the update). The
        log holds the update's metrics as NaN (their shapes traced once per learner). ``learn``
        False: no TD3 update (lines 12-15 run in ``td3_chunk``, one chunk behind: ``rollout``,
        d2spo/pipelined.py)."""
        def act(k, random_phase):
            u_rl = explore(self.nets, c.agent, c.obs, k["act"], random_phase,
                           self.cfg.noise_at(c.td3.episodes, self.schedule.per_episode), self.cfg.exploration_noise_space)
            ctx = self.filter_context(c.env_state) if self.d2.runtime_filter else None
            return u_rl, self.execute(c.safety, c.obs, u_rl, c.env_state.pose, ctx)

        step = explore_and_store(c.td3, ("act", "env", "update", "data", "safety"), act, self.env, self.params,
                                 self.schedule, self.num_envs, self.cfg.learning_starts)
        info, u_rl, action = step.info, step.proposal, step.action
        tr = sd.Transition(pose=info["pose"], next_pose=info["next_pose"], context=self.context(info),
                           obs=c.obs, action=action, u_rl=u_rl)
        data, data_stats = sd.update_datasets(c.data, step.keys["data"], tr, features_fn=self.features_for_grad, cfg=self.cbf_cfg)
        if learn:
            agent, metrics = learn_from_buffer(self.nets, c.agent, step.carry.buffer, step.keys["update"],
                                               step.carry.steps, self.num_envs, self.cfg, self._execute_fn(c.safety),
                                               self.d2.proposal_weight)
        else:
            agent, metrics = c.agent, no_updates()
        c = D2SPOCarry(step.carry.replace(agent=agent), c.safety, data)
        if self._safety_metrics is None:
            self._safety_metrics = jax.eval_shape(self._safety_update, c, step.keys["safety"])[1]
        metrics.update(jax.tree_util.tree_map(lambda t: jnp.full(t.shape, jnp.nan, t.dtype), self._safety_metrics))
        metrics["safety/override"] = jnp.mean(jnp.linalg.norm(action - u_rl, axis=-1))
        metrics["charts/label_radius"] = jnp.mean(step.params.label_radius)
        return c, episode_log(step.done, info, metrics), step.keys["safety"]

    def _execute_fn(self, safety: SafetyState):
        """π_Ω with ``safety``'s parameters, differentiable in u, for TD3's actor loss; None when the
        actor loss does not go through it (``actor_through_safety``)."""
        if self.d2.actor_through_safety is False:  # None: on (TrainConfig resolves it per learner)
            return None

        def execute_fn(o, u):
            return safe_action(self.safety_nets, safety, self.x_of_obs(o), u)
        return execute_fn

    def _safety_update(self, c: D2SPOCarry, k_safe: jax.Array):
        """UPDATE(Ω, Θ) after a step, on its datasets, with its RL proposal (the updated actor plus
        exploration noise) and its key: (safety state, metrics). Kept as it was until P_exp holds a
        batch (metrics NaN)."""
        def u_rl_fn(o):  # the current RL proposal, with exploration noise, as π_Ω will see it
            u = self.nets.actor.apply(c.agent.actor, o)
            std = self.cfg.noise_at(c.td3.episodes, self.schedule.per_episode)
            noise = std * jax.random.normal(jax.random.fold_in(k_safe, 1), u.shape)
            return jnp.clip(u + noise, self.nets.actor.action_low(), 1.0)

        new, metrics = update(k_safe, c.safety, c.data, nets=self.safety_nets, cfg=self.cbf_cfg,
                              features_fn=self.features_for_grad, dt=self.dt, u_rl_fn=u_rl_fn)
        enough = c.data.p_exp.size >= self.cbf_cfg.minibatch
        safety = jax.tree_util.tree_map(lambda a, b: jnp.where(enough, a, b), new, c.safety)
        return safety, jax.tree_util.tree_map(lambda v: jnp.where(enough, v, jnp.nan), metrics)

    def _with_update(self, c: D2SPOCarry, log: ChunkLog, k_safe: jax.Array) -> tuple[D2SPOCarry, ChunkLog]:
        """UPDATE(Ω, Θ) after a step; its metrics replace the NaN placeholders of the step's log (the
        log of that one step, or of a block that it ends: the last row)."""
        safety, s_metrics = self._safety_update(c, k_safe)
        metrics = dict(log.metrics)
        for k, v in s_metrics.items():
            metrics[k] = v if metrics[k].ndim == v.ndim else metrics[k].at[-1].set(v)
        return c.replace(safety=safety), log._replace(metrics=metrics)

    def chunk(self, carry: D2SPOCarry) -> tuple[D2SPOCarry, ChunkLog]:
        """``chunk_steps`` vectorised steps of Algorithm 1, lines 6-17, as one program."""
        return self._chunk(carry, learn=True)

    def _chunk(self, carry: D2SPOCarry, learn: bool) -> tuple[D2SPOCarry, ChunkLog]:
        every = self.d2.update_every
        if self.chunk_steps % every == 0:
            # Every chunk starts in phase: a scan over blocks of ``update_every`` steps, after the last
            # of which UPDATE(Ω, Θ) runs. The schedule is then in the program's structure, the same for
            # every seed under jax.vmap, and no lax.cond holds the update: inside a branch the update
            # cost the chunk ~60 ms, 3x its own time, and this layout takes 20% off a chunk (bench/RESULTS.md).
            # The step is traced once (the scan's body), not once more for the block's last step.
            def block(c, _):
                c, (log, keys) = jax.lax.scan(lambda c, _: self._step_out(c, learn), c, None, length=every)
                return self._with_update(c, log, keys[-1])

            carry, log = jax.lax.scan(block, carry, None, length=self.chunk_steps // every)
            log = jax.tree_util.tree_map(lambda a: a.reshape((self.chunk_steps,) + a.shape[2:]), log)
        else:  # the schedule from the step count: a branch
            def one(c, _):
                c, log, k_safe = self._step(c, learn)
                due = c.steps % every == 0
                return jax.lax.cond(due, lambda: self._with_update(c, log, k_safe), lambda: (c, log))

            carry, log = jax.lax.scan(one, carry, None, length=self.chunk_steps)
        finite = params_finite(carry.agent) & params_finite((carry.safety.cbf, carry.safety.policy, carry.safety.nominal))
        return carry, log._replace(nonfinite=jnp.any(log.nonfinite) | ~finite)

    def _step_out(self, c: D2SPOCarry, learn: bool = True):
        c, log, k_safe = self._step(c, learn)
        return c, (log, k_safe)

    # -- evaluation ----------------------------------------------------------------------
    def policy(self, carry: D2SPOCarry):
        return (carry.agent.actor, carry.safety)

    def act(self, policy, obs, env_state, key):
        actor, safety = policy
        u_rl = self.nets.actor.apply(actor, obs)
        ctx = self.filter_context(env_state) if self.d2.runtime_filter else None
        return self.execute(safety, obs, u_rl, env_state.pose, ctx)
