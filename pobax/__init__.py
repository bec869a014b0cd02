"""pobax: reinforcement learning under partial observability in JAX — memory-improvable environments with
partial / perfect-memory / full observabilities, memory-based PPO agents, and the benchmark of their gap.

    import pobax
    env = pobax.env.make("tmaze_10")
    result = pobax.train(pobax.agent.TrainConfig(env="tmaze_5", memory="gru"), out="runs/t")
    run = pobax.load_run("runs/t"); pobax.evaluate(run); pobax.render_episode(run, "episode.gif")
"""

from . import agent as agent
from . import env as env
from . import eval as eval  # noqa: A004 (the subpackage's name)
from . import memory as memory
from ._distributed import init_distributed as init_distributed
from ._version import __version__ as __version__
from .agent import TrainConfig as TrainConfig
from .eval import evaluate as evaluate
from .eval import load_run as load_run
from .eval import render_episode as render_episode
from .eval import train as train
