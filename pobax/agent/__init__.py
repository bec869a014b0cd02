"""Agents: networks, distributions, PPO / λ-discrepancy, and the compiled training loop."""

from ._config import NUMERIC as NUMERIC
from ._config import ConfigError as ConfigError
from ._config import Hyperparams as Hyperparams
from ._config import TrainConfig as TrainConfig
from ._config import validate as validate
from ._distributions import Categorical as Categorical
from ._distributions import DiagGaussian as DiagGaussian
from ._encoders import Flatten as Flatten
from ._encoders import FullImageCNN as FullImageCNN
from ._encoders import SmallImageCNN as SmallImageCNN
from ._encoders import make_encoder as make_encoder
from ._gae import gae as gae
from ._network import ActorCritic as ActorCritic
from ._network import make_memory as make_memory
from ._ppo import EpisodeStats as EpisodeStats
from ._ppo import TrainState as TrainState
from ._ppo import init_state as init_state
from ._ppo import make_model as make_model
from ._ppo import ppo_loss as ppo_loss
from ._ppo import rollout as rollout
from ._ppo import update as update
from ._train import TrainResult as TrainResult
from ._train import summarize as summarize
from ._train import train as train
