"""Where one D²SPO training chunk spends its time, piece by piece.

    .venv/bin/python bench/profile_chunk.py [--task phi1] [--layout paper] [--repeats 3] [--set td3.batch_size=256 ...]

The learner is warmed up past ``learning_starts`` (so every update runs), then each piece of one
vectorised step is compiled alone as a ``lax.scan`` over ``--steps`` calls on that realistic state
and timed (best of ``--repeats``, compile excluded): the env step, acting (π_rl and π_Ω), the replay
write, the safety datasets' update, one TD3 update (critic, and the delayed actor through π_Ω), and
one UPDATE(Ω, Θ) of Algorithm 1 (nominal model and Eq. (9) steps, divided by ``update_every`` as it
runs once per that many steps). The whole chunk is timed too, fused and pipelined (the rollout
and TD3's updates in two threads, ``--d2spo.pipeline``); the pieces need not sum to the fused one
exactly (XLA fuses across them in the chunk). The last line is one JSON object {piece: ms per vectorised step}.
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp

from d2spo import replay
from d2spo.algos.td3 import explore, learn_from_buffer
from d2spo.config import TrainConfig, config_from_dict, config_to_dict
from d2spo.pipelined import Pipelined
from d2spo.replay import Transition
from d2spo.run import build
from d2spo.safety import datasets as sd
from d2spo.safety.joint_policy import safe_action, update


def _with_overrides(cfg: TrainConfig, sets: list[str]) -> TrainConfig:
    data = config_to_dict(cfg)
    for s in sets:
        path, value = s.split("=", 1)
        node = data
        *head, last = path.split(".")
        for k in head:
            node = node[k]
        try:  # numbers, lists, true/false/null; anything else is a string
            node[last] = json.loads(value)
        except json.JSONDecodeError:
            node[last] = value
    return config_from_dict(data)


def _best(fn, arg, repeats: int) -> float:
    """Best wall time of ``fn`` over ``repeats`` calls, each on a fresh copy of ``arg`` made before the
    clock starts: ``fn`` donates its argument, as training's chunk does (d2spo/train.py). Without the
    donation every call copied its whole argument once (the replay buffer: 300,000 rows), which the
    250 steps of a call then shared: about 0.14 of the replay write's 0.16 ms per vectorised step was
    that copy (bench/RESULTS.md, "2026-12-03, late night")."""
    def fresh():
        return jax.block_until_ready(jax.tree_util.tree_map(jnp.copy, arg))

    jax.block_until_ready(fn(fresh()))
    best = float("inf")
    for _ in range(repeats):
        a = fresh()
        t0 = time.perf_counter()
        jax.block_until_ready(fn(a))
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="phi1")
    ap.add_argument("--layout", default="paper")
    ap.add_argument("--steps", type=int, default=250, help="vectorised steps per timed call")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--set", nargs="*", default=[], help="config overrides, e.g. td3.batch_size=256")
    ap.add_argument("--whole-only", action="store_true", help="time the whole chunk only")
    a = ap.parse_args()
    cfg = _with_overrides(TrainConfig(task=a.task), [f"env.layout={a.layout}", *a.set])
    env, params, L = build(cfg)
    chunk = jax.jit(L.chunk)
    carry = jax.jit(L.init)(jax.random.PRNGKey(0))
    warm_chunks = -(-cfg.td3.learning_starts // (cfg.num_envs * cfg.chunk_steps)) + 1
    for _ in range(warm_chunks):
        carry, log = chunk(carry)
    jax.block_until_ready(log.done)
    n = a.steps
    scale = 1e3 / n  # ms per vectorised step

    def scanned(body):
        return jax.jit(lambda c: jax.lax.scan(lambda c, _: (body(c), None), c, None, length=n)[0], donate_argnums=0)

    keys = jax.random.split(jax.random.PRNGKey(1), 4)
    u0 = jnp.zeros((cfg.num_envs, env.action_size))
    ep = L.schedule.env_params(L.params, carry.episodes)

    def env_step(s):
        k, es = s
        k, k1 = jax.random.split(k)
        es, *_ = env.step_batch(k1, es, u0, ep)
        return k, es

    def act(s):
        k, obs = s
        k, k1 = jax.random.split(k)
        u_rl = explore(L.nets, carry.agent, obs, k1, jnp.array(False), cfg.td3.exploration_noise)
        u = L.execute(carry.safety, obs, u_rl, carry.env_state.pose, None)
        return k, obs + 1e-6 * jnp.sum(u)

    o = carry.obs
    tr = Transition(o, u0, jnp.zeros(cfg.num_envs), jnp.zeros(cfg.num_envs), o, jnp.zeros(cfg.num_envs))

    def buffer_write(buf):
        return replay.add_batch(buf, tr)

    pose = carry.env_state.pose
    ctx = L.sensed(jnp.ones((cfg.num_envs, L.n_obstacles), bool))
    str_ = sd.Transition(pose=pose, next_pose=pose, context=ctx, obs=o, action=u0, u_rl=u0)

    def datasets(s):
        k, data = s
        k, k1 = jax.random.split(k)
        return k, sd.update_datasets(data, k1, str_, features_fn=L.features_for_grad, cfg=L.cbf_cfg)[0]

    def td3(s):
        k, agent = s
        k, k1 = jax.random.split(k)

        def execute_fn(ob, u):
            return safe_action(L.safety_nets, carry.safety, L.x_of_obs(ob), u)

        fn = execute_fn if L.d2.actor_through_safety else None
        agent, _ = learn_from_buffer(L.nets, agent, carry.buffer, k1, carry.steps + 1, cfg.num_envs, cfg.td3, fn,
                                     L.d2.proposal_weight)
        return k, agent

    def td3_plain(s):
        k, agent = s
        k, k1 = jax.random.split(k)
        agent, _ = learn_from_buffer(L.nets, agent, carry.buffer, k1, carry.steps + 1, cfg.num_envs, cfg.td3)
        return k, agent

    def safety(s):
        k, st = s
        k, k1 = jax.random.split(k)

        def u_rl_fn(ob):
            return L.nets.actor.apply(carry.agent.actor, ob)

        st, _ = update(k1, st, carry.data, nets=L.safety_nets, cfg=L.cbf_cfg, features_fn=L.features_for_grad, dt=L.dt,
                       u_rl_fn=u_rl_fn)
        return k, st

    every = cfg.d2spo.update_every
    pieces = {
        "env step": (scanned(env_step), (keys[0], carry.env_state), 1.0),
        "acting (pi_rl, pi_Omega)": (scanned(act), (keys[1], o), 1.0),
        "replay write (TD3 buffer)": (scanned(buffer_write), carry.buffer, 1.0),
        "safety datasets (T, P_exp, X_L)": (scanned(datasets), (keys[2], carry.data), 1.0),
        "TD3 update (actor through pi_Omega)": (scanned(td3), (keys[3], carry.agent), 1.0),
        "TD3 update (plain actor loss)": (scanned(td3_plain), (keys[3], carry.agent), 1.0),
        f"UPDATE(Omega, Theta) / {every}": (scanned(safety), (keys[0], carry.safety), 1.0 / every),
    }
    result = {}
    donated = jax.jit(L.chunk, donate_argnums=0)
    whole = _best(lambda c: donated(c)[1].done, carry, a.repeats)
    result["whole chunk"] = whole * 1e3 / cfg.chunk_steps
    # --d2spo.pipeline: the rollout and TD3's updates as two programs in two threads (d2spo/pipelined.py)
    piped = Pipelined(lambda name, donate: jax.jit(getattr(L, name), donate_argnums=0 if donate else ()), donate=True)
    result["pipelined chunk (rollout | TD3)"] = _best(lambda c: piped(c)[1].done, carry, a.repeats) * 1e3 / cfg.chunk_steps
    for name, (fn, arg, weight) in ({} if a.whole_only else pieces).items():
        result[name] = _best(fn, arg, a.repeats) * scale * weight
    print(f"config: {cfg.task} on {cfg.layout}, {cfg.num_envs} envs, overrides {a.set or 'none'}")
    for k, v in result.items():
        print(f"{k:40s} {v:8.3f} ms per vectorised step")
    print(json.dumps({k: round(v, 4) for k, v in result.items()}))


if __name__ == "__main__":
    main()
