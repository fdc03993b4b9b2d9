"""The navigation environment of the paper's Example 1 (see docs/env.md and docs/layouts.md).

Importing this package registers the Gymnasium id ``d2spo/Nav-v0`` (see ``gym_env``) when
gymnasium >= 1.1 is installed (``pip install 'd2spo[gym]'``). gymnasium is optional: without it,
or beside an older one, the functional env (``make_env``) and the gymnax-style env work as usual
and only the Gymnasium classes below raise an ImportError that says what to install.
"""

from d2spo.envs import layouts
from d2spo.envs.env_config import EnvConfig
from d2spo.envs.nav import Env, EnvState, make_env
from d2spo.envs.params import EnvParams
from d2spo.envs.workspace import Layout

_GYMNASIUM_NAMES = ("CostTuple", "NavEnv", "NavVectorEnv", "VectorCostTuple")

try:
    from d2spo.envs.gym_env import CostTuple, NavEnv, NavVectorEnv, VectorCostTuple, register
except ImportError as missing:
    if missing.name != "gymnasium":
        raise
    _gymnasium_missing = missing
else:
    register()


def __getattr__(name: str):
    if name in _GYMNASIUM_NAMES:
        raise ImportError(str(_gymnasium_missing), name="gymnasium")
    raise AttributeError(f"module 'd2spo.envs' has no attribute {name!r}")


__all__ = [
    "CostTuple", "Env", "EnvConfig", "EnvParams", "EnvState", "Layout", "NavEnv", "NavVectorEnv", "VectorCostTuple",
    "layouts", "make_env",
]
