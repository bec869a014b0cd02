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


# DeepMind Lab mazes on NAVIX. One family per maze: the time limit, the recommended settings and the best
# hyperparameters differ between mazes, and an `EnvFamily` holds one of each. NAVIX is imported only when
# a maze is built (the `navix` extra).
def _dmlab_maze_family(maze_id: str, recommended: dict, best: dict) -> EnvFamily:
    from ._dmlab_maze import MAX_STEPS, ORACLE_VALUES, DMLabMaze

    name = f"Navix-DMLab-Maze-{maze_id}-v0"
    return register(
        EnvFamily(
            template=name,
            pattern=rf"Navix-DMLab-Maze-(?P<maze_id>{maze_id})-v0",
            # `EnvFamily.match` turns "01" into 1: format it back.
            build=lambda observability, maze_id, **kw: DMLabMaze(f"{int(maze_id):02d}", observability, **kw),
            observabilities=DMLabMaze.observabilities,
            categories=("spatial uncertainty", "episode nonstationarity"),
            max_steps=MAX_STEPS[maze_id],
            registered=(name,),
            recommended=recommended,
            best=best,
            reference=lambda env: dict(ORACLE_VALUES[env.unwrapped.maze_id]),
            extra="navix",
        )
    )


# Paper appendix "DeepMind Lab MiniGrid mazes": hidden size 512, TrXL embed size 220; 256 envs and 10M steps
# for maze 01, 512 envs and 100M steps for maze 02; other general settings are the defaults. The paper did
# not train on maze 03 (too hard); it gets maze 02's settings and no best hyperparameters.
_MAZE_02_RECOMMENDED = dict(hidden_size=512, num_envs=512, total_steps=100_000_000, entropy_coeff=0.01, embed_size=220)
DMLAB_MAZE_01 = _dmlab_maze_family(
    "01",
    recommended=dict(hidden_size=512, num_envs=256, total_steps=10_000_000, entropy_coeff=0.01, embed_size=220),
    # Paper table "DeepMind Lab MiniGrid Maze Level 1 Best Hyperparameters".
    best={
        "full": dict(lr=2.5e-4, lambda0=0.95),
        "memoryless": dict(lr=2.5e-4, lambda0=0.95),
        "gru": dict(lr=2.5e-4, lambda0=0.9, action_concat=True),
        "trxl": dict(lr=2.5e-4, lambda0=0.95, action_concat=True),
        "ld": dict(lr=2.5e-4, lambda0=0.95, lambda1=0.5, ld_weight=0.25, action_concat=True),
    },
)
DMLAB_MAZE_02 = _dmlab_maze_family(
    "02",
    recommended=_MAZE_02_RECOMMENDED,
    # Paper table "DeepMind Lab MiniGrid Maze Level 2 Best Hyperparameters".
    best={
        "full": dict(lr=2.5e-4, lambda0=0.95),
        "memoryless": dict(lr=2.5e-3, lambda0=0.95),
        "gru": dict(lr=2.5e-4, lambda0=0.95, action_concat=True),
        "trxl": dict(lr=2.5e-4, lambda0=0.95, action_concat=True),
        "ld": dict(lr=2.5e-4, lambda0=0.95, lambda1=0.95, ld_weight=0.25, action_concat=True),
    },
)
DMLAB_MAZE_03 = _dmlab_maze_family("03", recommended=dict(_MAZE_02_RECOMMENDED), best={})
