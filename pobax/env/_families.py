"""Registration of the built-in environment families."""

from ._registry import EnvFamily, register
from ._tmaze import TMaze

TMAZE = register(
    EnvFamily(
        template="tmaze_{n}",
        pattern=r"tmaze_(?P<length>\d+)",
        build=lambda observability, length, **kw: TMaze(length=length, observability=observability, **kw),
        observabilities=TMaze.observabilities,
        categories=("object uncertainty & tracking",),
        max_steps=1000,
        registered=("tmaze_10",),
        # Paper appendix, T-Maze: hidden size 32, 1M steps; other general settings are the defaults.
        recommended=dict(hidden_size=32, num_envs=4, total_steps=1_000_000, entropy_coeff=0.01, embed_size=12),
        # Paper table "T-Maze 10 Best Hyperparameters".
        best={
            "full": dict(lr=2.5e-4, lambda0=0.5),
            "memoryless": dict(lr=2.5e-4, lambda0=0.3),
            "gru": dict(lr=2.5e-3, lambda0=0.7, action_concat=True),
            "trxl": dict(lr=2.5e-4, lambda0=0.9, action_concat=True),
            "ld": dict(lr=2.5e-4, lambda0=0.95, lambda1=0.95, ld_weight=0.5, action_concat=True),
        },
        reference=lambda env: {
            "optimal_discounted_return": env.optimal_return(),
            "memoryless_discounted_return": env.memoryless_return(),
            "optimal_undiscounted_return": 4.0,
        },
    )
)
