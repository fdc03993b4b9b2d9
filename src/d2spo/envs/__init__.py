"""The navigation environment of the paper's Example 1 (see docs/env.md and docs/layouts.md).

Importing this package registers the Gymnasium id ``d2spo/Nav-v0`` (see ``gym_env``).
"""

from d2spo.envs import layouts
from d2spo.envs.env_config import EnvConfig
from d2spo.envs.gym_env import (
    CostTuple,
    NavEnv,
    NavVectorEnv,
    VectorCostTuple,
    register,
)
from d2spo.envs.layouts import Layout
from d2spo.envs.nav import Env, EnvParams, EnvState, make_env

register()

__all__ = [
    "CostTuple", "Env", "EnvConfig", "EnvParams", "EnvState", "Layout", "NavEnv", "NavVectorEnv", "VectorCostTuple",
    "layouts", "make_env",
]
