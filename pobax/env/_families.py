"""Registration of the built-in environment families."""

from .._backend import reset_pool_size
from ._registry import EnvFamily, discrepancy_terms, register
from ._wrappers import AutoReset
from ._tmaze import TMaze

TMAZE = register(
    EnvFamily(
        template="tmaze_{n}",
        pattern=r"tmaze_(?P<length>(?:0|[1-9][0-9]*))",
        build=lambda observability, length, **kw: TMaze(length=length, observability=observability, **kw),
        observabilities=TMaze.observabilities,
        categories=("object uncertainty & tracking",),
        max_steps=1000,
        registered=("tmaze_10",),
                # (No Transformer-XL size in the appendix: `paper_original` has the default table's 256; 12 is pobax's.)
        recommended=dict(hidden_size=32, num_envs=4, total_steps=1_000_000, entropy_coeff=0.01, embed_size=12),
        # Paper table "T-Maze 10 Best Hyperparameters".
        # Except the ceiling's λ0: at the paper's 0.5, 6 of 30 seeds never reach the junction's reward (final
        # 2.865 [2.268, 3.342] against the optimum 3.581). The paper's sweep (4 step sizes × 6 λ0) on 30 seeds,
        # selected by AUC, picks λ0 0.9 at the same step size: 30 of 30 seeds optimal (H200,
        # benchmarks/results/tmaze10-ceiling-sweep-h200.json).
        best={
            "full": dict(lr=2.5e-4, lambda0=0.9),
            "memoryless": dict(lr=2.5e-4, lambda0=0.3),
            "gru": dict(lr=2.5e-3, lambda0=0.7, action_concat=True),
            "trxl": dict(lr=2.5e-4, lambda0=0.9, action_concat=True),
            "ld": dict(lr=2.5e-4, lambda0=0.95, lambda1=0.95, ld_weight=0.5, action_concat=True),
            # The memory zoo (not in the paper): the paper's sweep (4 step sizes × 6 λ0, 5 seeds, AUC) at the GRU's
            # other settings, on the CPU (benchmarks/results/zoo-tmaze10-sweep-cpu.json).
            "lru": dict(lr=2.5e-3, lambda0=0.1, action_concat=True),
            "s6": dict(lr=2.5e-3, lambda0=0.9, action_concat=True),
            "lstm": dict(lr=2.5e-3, lambda0=0.95, action_concat=True),
            "ffm": dict(lr=2.5e-4, lambda0=0.7, action_concat=True),
        },
        paper_original={"recommended": dict(embed_size=256), "full": dict(lambda0=0.5)},
        budgets={"reduced": dict(total_steps=1_000_000, num_seeds=30)},
        # ceiling / GRU / λ-discrepancy / Transformer-XL / floor, discounted (paper's results figure).
        paper_figure=dict(ceiling=3.5, gru=2.8, ld=3.3, trxl=3.5, floor=1.75),
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
#: The paper's maze sweeps (appendix, "DeepMind Lab MiniGrid Maze hyperparameters swept").
MAZE_GRID = {"lr": (2.5e-3, 2.5e-4, 2.5e-5, 2.5e-6), "lambda0": (0.1, 0.5, 0.7, 0.9, 0.95)}
MAZE_LD_GRID = {"lr": (2.5e-4, 2.5e-5), "lambda0": (0.1, 0.95), "lambda1": (0.5, 0.7, 0.95), "ld_weight": (0.25, 0.5)}


def _dmlab_maze_family(maze_id: str, recommended: dict, best: dict, budget: dict, figure: dict) -> EnvFamily:
    from ._dmlab_maze import MAX_STEPS, ORACLE_VALUES, RANDOM_POLICY_VALUES, DMLabMaze

    name = f"Navix-DMLab-Maze-{maze_id}-v0"
    return register(
        EnvFamily(
            template=name,
            pattern=rf"Navix-DMLab-Maze-(?P<maze_id>{maze_id})-v0",
            build=lambda observability, maze_id, **kw: DMLabMaze(f"{int(maze_id):02d}", observability, **kw),
            observabilities=DMLabMaze.observabilities,
            categories=("spatial uncertainty", "episode nonstationarity"),
            max_steps=MAX_STEPS[maze_id],
            registered=(name,),
            recommended=recommended,
            best=best,
            reference=lambda env: {**ORACLE_VALUES[env.unwrapped.maze_id],
                                   **RANDOM_POLICY_VALUES[env.unwrapped.maze_id]},
            extra="navix",
            # The paper's ceiling (memoryless on the agent-centric map, one pixel per cell, `--observability full`)
            # reads the map flattened. The paper's FullImageCNN (7x7 stride-4 first layer, 64 features after its 4th
            # convolution) was not a reliable ceiling: maze 01, 10M steps, 4 seeds, paper settings, H200
            # (benchmarks/results/gap-maze01-10M-h200.json): CNN 0.445 [0.349, 0.544] (another run: 0.498 at 6.8M),
            # flattened 0.599 [0.563, 0.640], GRU on the partial view 0.513 [0.506, 0.520]. `--encoder full_cnn` is
            # the paper's.
            ceiling_encoder="flatten",
            # The registry's ceiling reads `perfect_memory` (the view, the agent's pose and the goal's cell, one-hot):
            # on the map, maze 02's stayed at the random policy's 0.035 to 100M steps whatever was tried; on
            # `perfect_memory`, 20M x 5, H200: maze 02 0.291 [0.222, 0.361], maze 01 0.753 (map 0.614); maze 03 0.023,
            # random level (benchmarks/results/maze-perfect-memory-ceiling-h200.json, docs/deviations.md).
            ceiling_observability="perfect_memory",
            paper_original={"full": dict(encoder="auto")},
            budgets={"reduced": budget},
            paper_figure=figure,
            # The paper's maze sweeps, and its ceiling: memoryless on the map through the paper's encoder.
            paper_protocol={"grid": MAZE_GRID, "ld_grid": MAZE_LD_GRID,
                            "ceiling": {"observability": "full", "memory": "memoryless", "encoder": "auto"}},
        )
    )


# Paper appendix "DeepMind Lab MiniGrid mazes": hidden size 512, TrXL embed size 220; 256 envs and 10M steps
# for maze 01, 512 envs and 100M steps for maze 02; other general settings are the defaults. The paper did
# not train on maze 03 (too hard); it gets maze 02's settings and no best hyperparameters, but for the
# λ-discrepancy agent's own two (λ1, β: maze 02's), without which it would be a GRU with two critics and no
# discrepancy loss (the defaults' β = 0). Its other settings are the defaults, as for its GRU.
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
    budget=dict(total_steps=10_000_000, num_seeds=10),
    figure=dict(ceiling=0.65, gru=0.49, ld=0.48, trxl=0.49, floor=0.34),
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
    budget=dict(total_steps=20_000_000, num_seeds=5),
    figure=dict(ceiling=0.46, gru=0.24, ld=0.22, trxl=0.24, floor=0.17),
)
DMLAB_MAZE_03 = _dmlab_maze_family("03", recommended=dict(_MAZE_02_RECOMMENDED),
                                   best=discrepancy_terms(DMLAB_MAZE_02.best),
                                   budget=dict(total_steps=20_000_000, num_seeds=5), figure={})

# Masked MuJoCo (Brax/MJX): `Walker-V-v0`, `HalfCheetah-V-v0` and the `{robot}-{F,P,V}-v0` family.
from ._mujoco_families import masked_mujoco_families  # noqa: E402

MASKED_MUJOCO = [register(f) for f in masked_mujoco_families()]


def pooled_auto_reset(env):
    """`AutoReset` for RockSample and Battleship, whose resets (random draws; Battleship's placement sampling) cost
    about a step or more while episodes last tens of steps: the platform's pool size (`pobax._backend.reset_pool_size`:
    done environments reset 8 at a time on the CPU, every environment each step on accelerators), set by
    `pobax.env.for_backend` (training does); the CPU's until then. The same episodes either way (`AutoReset`)."""
    return AutoReset(env, pool_size=reset_pool_size("cpu"), pool_by_platform=True)


# RockSample (n, k). One family per paper ID (their recommended settings and best hyperparameters differ,
# and an `EnvFamily` holds one of each), then the general `rocksample_{n}_{k}` with 11_11's settings.
from ._rocksample import EXIT_REWARD, RockSample  # noqa: E402


def _rocksample_family(template: str, pattern: str, registered: tuple, recommended: dict, best: dict,
                       paper_original: dict, budget: dict, figure: dict, paper_protocol: dict | None = None):
    # The paper's RockSample ceiling ("full" row of its tables) is a GRU on the perfect-memory observation.
    return register(
        EnvFamily(
            template=template,
            pattern=pattern,
            build=lambda observability, size, num_rocks, **kw: RockSample(
                size, num_rocks, observability, **kw
            ),
            observabilities=RockSample.observabilities,
            categories=("object uncertainty & tracking",),
            max_steps=1000,
            registered=registered,
            recommended=recommended,
            best=best,
            ceiling_memory="gru",
            ceiling_observability="perfect_memory",
            auto_reset=pooled_auto_reset,
            paper_original=paper_original,
            budgets={"reduced": budget},
            paper_figure=figure,
            paper_protocol=paper_protocol or {},
            reference=lambda env: {"exit_at_once_discounted_return": env.exit_at_once_return(),
                                   "exit_at_once_undiscounted_return": EXIT_REWARD},
        )
    )


# Paper appendix "Rocksample": hidden 256, 8 envs, entropy 0.2 for (11, 11); hidden 512, 16 envs for (15, 15); no
# Transformer-XL size (the default table's 256 is `paper_original`'s; 96 and 220 here are pobax's). The paper's "full"
# row is a GRU on `perfect_memory`. Reward normalisation is the original implementation's, under both presets: its
# environment factory wraps RockSample, and only RockSample, in a reward normaliser whatever its `normalize_env` says
# (docs/parity.md); the paper does not mention it. 32 envs per seed are pobax's (docs/deviations.md).
_ROCKSAMPLE_11_RECOMMENDED = dict(
    hidden_size=256, num_envs=32, total_steps=5_000_000, entropy_coeff=0.2, embed_size=96, normalize_reward=True
)
ROCKSAMPLE_11_11 = _rocksample_family(
    "rocksample_11_11",
    r"rocksample_(?P<size>11)_(?P<num_rocks>11)",
    ("rocksample_11_11",),
    _ROCKSAMPLE_11_RECOMMENDED,
    # Paper table "Rocksample(11, 11) Best Hyperparameters", except the two GRU agents (docs/deviations.md).
    best={
        "full": dict(lr=2.5e-3, lambda0=0.3, action_concat=True),
        "memoryless": dict(lr=2.5e-3, lambda0=0.3),
        "gru": dict(lr=2.5e-3, lambda0=0.3, action_concat=True),
        "trxl": dict(lr=2.5e-4, lambda0=0.1, action_concat=True),
        "ld": dict(lr=2.5e-3, lambda0=0.1, lambda1=0.95, ld_weight=0.25, action_concat=True),
        # The memory zoo (not in the paper): the paper's sweep (4 step sizes × 6 λ0, 5 seeds × 5M, AUC) at the GRU's
        # other settings; final discounted return of the selected set: S6 24.3, LSTM 22.8, FFM 19.6, LRU 18.0 (H200,
        # benchmarks/results/zoo-sweeps-rs11-bs10-h200.json, zoo-sweeps-lstm-rs11-bs10-h200.json).
        "lstm": dict(lr=2.5e-3, lambda0=0.7, action_concat=True),
        "lru": dict(lr=2.5e-3, lambda0=0.7, action_concat=True),
        "s6": dict(lr=2.5e-3, lambda0=0.5, action_concat=True),
        "ffm": dict(lr=2.5e-4, lambda0=0.5, action_concat=True),
    },
    paper_original={"recommended": dict(num_envs=8, embed_size=256),
                    "full": dict(lr=2.5e-4, lambda0=0.5), "gru": dict(lr=2.5e-4, lambda0=0.95)},
    budget=dict(total_steps=5_000_000, num_seeds=10),
    figure=dict(ceiling=20.0, gru=12.5, ld=12.5, trxl=11.0, floor=8.3),
)
ROCKSAMPLE_15_15 = _rocksample_family(
    "rocksample_15_15",
    r"rocksample_(?P<size>15)_(?P<num_rocks>15)",
    ("rocksample_15_15",),
    dict(hidden_size=512, num_envs=32, total_steps=10_000_000, entropy_coeff=0.2, embed_size=220,
         normalize_reward=True),
    # Paper table "Rocksample(15, 15) Best Hyperparameters", except the three GRU agents and the environments per
    # seed (docs/deviations.md).
    best={
        "full": dict(lr=2.5e-3, lambda0=0.3, action_concat=True),
        "memoryless": dict(lr=2.5e-3, lambda0=0.3),
        "gru": dict(lr=2.5e-3, lambda0=0.3, action_concat=True),
        "trxl": dict(lr=2.5e-5, lambda0=0.3, action_concat=True),
        "ld": dict(lr=2.5e-3, lambda0=0.1, lambda1=0.95, ld_weight=0.25, action_concat=True),
    },
    paper_original={"recommended": dict(num_envs=16, embed_size=256),
                    "full": dict(lr=2.5e-4, lambda0=0.7, action_concat=False),
                    "gru": dict(lr=2.5e-4, lambda0=0.95),
                    "ld": dict(lr=2.5e-4, lambda0=0.5, lambda1=0.5)},
    # The paper's text trains RockSample (15, 15) for 5M steps, its figure for 10M (the recommended setting).
    budget=dict(total_steps=5_000_000, num_seeds=10),
    figure=dict(ceiling=21.5, gru=13.0, ld=12.0, trxl=9.2, floor=7.7),
    paper_protocol={"total_steps": 5_000_000},
)
ROCKSAMPLE = _rocksample_family(
    "rocksample_{n}_{k}",
    r"rocksample_(?P<size>(?:0|[1-9][0-9]*))_(?P<num_rocks>(?:0|[1-9][0-9]*))",
    (),
    dict(_ROCKSAMPLE_11_RECOMMENDED, embed_size=220),
    discrepancy_terms(ROCKSAMPLE_11_11.best),
    paper_original={},
    budget=dict(total_steps=5_000_000, num_seeds=10),
    figure={},
)


# Battleship(n): ships 5, 4, 3, 2 on an n x n board. The paper's ceiling is the probability-search policy's mean
# return (here measured: `_battleship_oracle.ORACLE_RESULTS`, a reference line); the gap report and the benchmark
# also train a ceiling agent, a memoryless MLP on the perfect-memory board (every hit and miss so far), with the
# paper's memoryless hyperparameters (its table has no row for it).
from ._battleship import Battleship  # noqa: E402
from ._battleship_oracle import reference_values as _battleship_reference  # noqa: E402

BATTLESHIP = register(
    EnvFamily(
        template="battleship_{n}",
        pattern=r"battleship_(?P<size>(?:0|[1-9][0-9]*))",
        build=lambda observability, size, **kw: Battleship(size, observability=observability, **kw),
        observabilities=Battleship.observabilities,
        categories=("spatial uncertainty", "episode nonstationarity"),
        # The environment truncates at n * n shots itself (the bound depends on n); no extra time limit.
        max_steps=None,
        registered=("battleship_10",),
        # Paper appendix "Battleship": hidden 512, 32 envs, entropy 0.05, 10M steps; TrXL embed 220.
        recommended=dict(
            hidden_size=512, num_envs=32, total_steps=10_000_000, entropy_coeff=0.05, embed_size=220
        ),
        # Paper table "Battleship Best Hyperparameters" (no "full" row: the ceiling is the oracle). The
        # partial observation already ends with the one-hot of the last action, so no `action_concat`.
        # The paper's Battleship RNN has the extra dense layer: `extra_dense=True`.
        # The ceiling's row is not the paper's (a trained agent; docs/deviations.md).
        best={
            "full": dict(lr=1e-4, lambda0=0.1, entropy_coeff=0.1),
            "memoryless": dict(lr=2.5e-3, lambda0=0.1),
            "gru": dict(lr=2.5e-3, lambda0=0.7, extra_dense=True),
            "trxl": dict(lr=2.5e-5, lambda0=0.1),
            "ld": dict(lr=2.5e-3, lambda0=0.1, lambda1=0.95, ld_weight=0.5),
            # The memory zoo (not in the paper): the paper's sweep (4 step sizes × 6 λ0, 5 seeds × 10M, AUC) at the
            # GRU's other settings; final return of the selected set: S6 13.2, LSTM 11.9, FFM 10.9, LRU 10.5 (H200,
            # benchmarks/results/zoo-sweeps-rs11-bs10-h200.json, zoo-sweeps-lstm-rs11-bs10-h200.json).
            "lstm": dict(lr=2.5e-4, lambda0=0.7, extra_dense=True),
            "lru": dict(lr=2.5e-3, lambda0=0.9, extra_dense=True),
            "s6": dict(lr=2.5e-4, lambda0=0.3, extra_dense=True),
            "ffm": dict(lr=2.5e-4, lambda0=0.1, extra_dense=True),
        },
        reference=_battleship_reference,
        ceiling_observability="perfect_memory",
        paper_original={"recommended": dict(embed_size=256),
                        "full": dict(lr=2.5e-3, lambda0=0.1, entropy_coeff=0.05)},
        # The paper sweeps Battleship with 10 seeds per set; its ceiling is the probability-search policy's return.
        paper_protocol={"selection_seeds": 10, "ceiling": {"reference": "oracle_mean_return"}},
        auto_reset=pooled_auto_reset,
        budgets={"reduced": dict(total_steps=10_000_000, num_seeds=10)},
        # Undiscounted (γ = 1). The paper's ceiling (46) is its belief-policy value; ours is a trained agent.
        paper_figure=dict(ceiling=46.0, gru=12.0, ld=19.5, trxl=9.5, floor=7.5),
        paper_metric="return",
    )
)


# Visual continuous control (pixel MuJoCo): `ant_pixels`, `halfcheetah_pixels`, `hopper_pixels`,
# `walker2d_pixels`. Frames come from a pure-JAX ray caster; Brax is imported lazily when an environment is
# built, so registering needs no extra dependency.
from ._pixels import pixel_mujoco_families  # noqa: E402

PIXEL_MUJOCO = [register(f) for f in pixel_mujoco_families()]


# No-inventory Crafter (`craftax_pixels`, paper appendix "No-inventory Crafter"). Craftax is imported lazily
# when the environment is built; its family resets only the done environments (`AutoReset(env, pool_size=8)`).
from ._craftax import craftax_families  # noqa: E402

CRAFTAX = [register(f) for f in craftax_families()]
