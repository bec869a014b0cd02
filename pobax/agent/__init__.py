"""Agents: networks, distributions, PPO / λ-discrepancy, and the compiled training loop (`Runs`).

`pobax.eval.train` (also `pobax.train`) drives the loop with a run directory, checkpoints and a summary.
"""

from ._cache import enable_compile_cache as enable_compile_cache
from ._config import NUMERIC as NUMERIC
from ._config import ConfigError as ConfigError
from ._config import Hyperparams as Hyperparams
from ._config import TrainConfig as TrainConfig
from ._config import config_differences as config_differences
from ._config import config_from_dict as config_from_dict
from ._config import env_kwargs as env_kwargs
from ._config import make_env as make_env
from ._validate import validate as validate
from ._distributions import Categorical as Categorical
from ._distributions import DiagGaussian as DiagGaussian
from ._encoders import Egocentric as Egocentric
from ._encoders import Flatten as Flatten
from ._encoders import MLPEncoder as MLPEncoder
from ._encoders import FullImageCNN as FullImageCNN
from ._encoders import SmallImageCNN as SmallImageCNN
from ._encoders import make_encoder as make_encoder
from ._gae import gae as gae
from ._network import ActorCritic as ActorCritic
from ._network import make_memory as make_memory
from ._network import unread_fields as unread_fields
from ._ppo import EpisodeStats as EpisodeStats
from ._ppo import ObsNorm as ObsNorm
from ._ppo import RewardNorm as RewardNorm
from ._ppo import TrainState as TrainState
from ._ppo import init_state as init_state
from ._ppo import make_model as make_model
from ._ppo import policy_step as policy_step
from ._ppo import ppo_loss as ppo_loss
from ._ppo import rollout as rollout
from ._ppo import update as update
from ._presets import apply_preset as apply_preset
from ._presets import load_preset as load_preset
from ._presets import paper_preset as paper_preset
from ._presets import resolve_preset as resolve_preset
from ._train import Chunk as Chunk
from ._train import Runs as Runs
from ._train import run_layout as run_layout
from ._train import structural as structural
