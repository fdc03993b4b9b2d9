"""Building blocks shared by every algorithm: networks, buffers, GAE, losses, Lagrange multiplier.

Modules with colliding function names (``lagrange.update``, ``normalize.update``) are best used
through the module: ``from d2spo.algos.common import lagrange``.
"""

from d2spo.algos.common import (
    gae,
    lagrange,
    networks,
    normalize,
    replay,
    rollout,
    sac_losses,
    td3_losses,
)
from d2spo.algos.common.gae import discounted_cumsum
from d2spo.algos.common.lagrange import LagrangeConfig, LagrangeState
from d2spo.algos.common.networks import (
    MLP,
    DeterministicActor,
    GaussianActor,
    GaussianPolicy,
    QNetwork,
    TwinQ,
    ValueNetwork,
    gaussian_entropy,
    gaussian_kl,
    gaussian_log_prob,
    gaussian_sample,
    init_params,
    tanh_gaussian_log_prob,
    tanh_gaussian_sample,
)
from d2spo.algos.common.normalize import RunningMeanStd
from d2spo.algos.common.replay import ReplayBuffer, Transition
from d2spo.algos.common.rollout import flatten_time_env, minibatches
from d2spo.algos.common.td3_losses import (
    cost_critic_loss,
    soft_update,
    td3_actor_loss,
    td3_critic_loss,
)

__all__ = [
    "MLP",
    "DeterministicActor",
    "GaussianActor",
    "GaussianPolicy",
    "LagrangeConfig",
    "LagrangeState",
    "QNetwork",
    "ReplayBuffer",
    "RunningMeanStd",
    "Transition",
    "TwinQ",
    "ValueNetwork",
    "cost_critic_loss",
    "discounted_cumsum",
    "flatten_time_env",
    "gae",
    "gaussian_entropy",
    "gaussian_kl",
    "gaussian_log_prob",
    "gaussian_sample",
    "init_params",
    "lagrange",
    "minibatches",
    "networks",
    "normalize",
    "replay",
    "rollout",
    "sac_losses",
    "soft_update",
    "tanh_gaussian_log_prob",
    "tanh_gaussian_sample",
    "td3_actor_loss",
    "td3_critic_loss",
    "td3_losses",
]
