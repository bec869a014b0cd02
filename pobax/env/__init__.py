"""Environments, spaces, wrappers and the registry."""

from . import _families as _families  # registers the built-in environments
from ._base import AbstractEnvironment as AbstractEnvironment
from ._base import AbstractWrapper as AbstractWrapper
from ._base import TimeStep as TimeStep
from ._base import action_mask as action_mask
from ._base import observation_array as observation_array
from ._base import timestep as timestep
from ._registry import EnvFamily as EnvFamily
from ._registry import EnvSpec as EnvSpec
from ._registry import UnknownEnvironmentError as UnknownEnvironmentError
from ._registry import make as make
from ._registry import register as register
from ._registry import registered_names as registered_names
from ._registry import spec as spec
from ._spaces import AbstractSpace as AbstractSpace
from ._spaces import Box as Box
from ._spaces import DictSpace as DictSpace
from ._spaces import Discrete as Discrete
from ._tmaze import TMaze as TMaze
from ._tmaze import TMazeState as TMazeState
from ._wrappers import ActionConcat as ActionConcat
from ._wrappers import AutoReset as AutoReset
from ._wrappers import TimeLimit as TimeLimit
from ._wrappers import TimeLimitState as TimeLimitState
