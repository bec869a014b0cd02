# %% [markdown]
# # Train and plot from Python
#
# Train a GRU agent and a memoryless one on T-Maze 5 with a few seeds, read their summaries and metrics, and plot
# their learning curves with 95% CIs. About a minute on 2 CPU cores; `POBAX_EXAMPLE_TINY=1` shrinks it to seconds
# (and to meaningless returns). Run directories go under `$POBAX_EXAMPLE_OUT` (default `runs/examples`).

# %%
import dataclasses
import datetime
import os
from pathlib import Path

import pobax
from pobax.agent import TrainConfig

TINY = os.environ.get("POBAX_EXAMPLE_TINY") == "1"
OUT = Path(os.environ.get("POBAX_EXAMPLE_OUT", "runs/examples"))
STAMP = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")

# %% [markdown]
# ## The configuration
# `TrainConfig` holds everything that defines a run; list-valued hyperparameters (here two step sizes) are trained
# together with every seed in one compiled program. `pobax.agent.paper_preset` gives the paper's settings.

# %%
gru = TrainConfig(env="tmaze_5", memory="gru", action_concat=True, hidden_size=32, lambda0=0.7,
                  lr=(2.5e-3, 2.5e-4), num_seeds=3, total_steps=150_000, num_chunks=5)
if TINY:
    gru = dataclasses.replace(gru, hidden_size=8, num_envs=2, num_steps=16, num_minibatches=2, total_steps=128,
                              num_seeds=2, num_chunks=1, fast_compile=True)
floor = dataclasses.replace(gru, memory="memoryless", action_concat=False, lr=(2.5e-4,))

# %% [markdown]
# ## Train
# Each call writes a run directory (configuration, metrics, checkpoints while it runs, the model, a summary).

# %%
results = {}
for name, cfg in (("gru", gru), ("memoryless", floor)):
    results[name] = pobax.train(cfg, OUT / f"tmaze5-{name}-{STAMP}", progress=not TINY)
    best = results[name].summary["sets"][results[name].summary["best_by_auc"]]
    d = best["disc_return"]
    print(f"{name}: best set lr={best['lr']:g}: final discounted return {d['mean']:.3f} "
          f"[{d['ci_low']:.3f}, {d['ci_high']:.3f}] over {best['num_seeds']} seeds -> {results[name].run_dir}")

# %% [markdown]
# ## The metrics table
# One row per (hyperparameter set, seed, update): returns, losses, entropy, ...

# %%
metrics = results["gru"].metrics
print(metrics.groupby(["hp_index", "update"])["disc_return"].mean().unstack(0).tail())

# %% [markdown]
# ## Learning curves
# `plot_runs` takes a run directory or a list of them (each run's best set by AUC with `best=True`).

# %%
figure = pobax.eval.plot_runs([r.run_dir for r in results.values()], OUT / f"tmaze5-curves-{STAMP}.png", best=True)
print("figure:", figure)
