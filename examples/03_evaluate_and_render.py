# %% [markdown]
# # Evaluate and watch a trained agent
#
# Load a run directory, measure its agents on fresh episodes, watch one episode, and call its network by hand.
# `python examples/03_evaluate_and_render.py RUN_DIR` uses your run; without one it first trains a GRU agent on
# T-Maze 5 (about 20 s on 2 CPU cores; `POBAX_EXAMPLE_TINY=1`: a few updates, meaningless returns).

# %%
import datetime
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

import pobax
from pobax.agent import TrainConfig

TINY = os.environ.get("POBAX_EXAMPLE_TINY") == "1"
OUT = Path(os.environ.get("POBAX_EXAMPLE_OUT", "runs/examples"))

if len(sys.argv) > 1 and not sys.argv[1].startswith("-"):
    run_dir = Path(sys.argv[1])
else:
    cfg = TrainConfig(env="tmaze_5", memory="gru", action_concat=True, hidden_size=32, lr=2.5e-3, lambda0=0.7,
                      num_seeds=2, total_steps=128 if TINY else 150_000, num_chunks=1 if TINY else 5,
                      fast_compile=TINY, **(dict(num_envs=2, num_steps=16, num_minibatches=2) if TINY else {}))
    run_dir = OUT / f"tmaze5-gru-{datetime.datetime.now():%Y%m%d-%H%M%S}"
    pobax.train(cfg, run_dir, progress=not TINY)

# %% [markdown]
# ## Load
# `load_run` reads a finished run (`model.eqx`) or an interrupted one (its last checkpoint): the configuration, the
# environment, every run's network stacked along a leading axis, the metrics and the summary.

# %%
run = pobax.load_run(run_dir)
print(f"{run.config.env} {run.config.memory}: {run.num_runs} runs ({run.source}); best set by AUC: {run.best_set}")

# %% [markdown]
# ## Evaluate on fresh episodes
# Every run plays the same episodes (deterministic for a seed); returns are averaged per seed, then over seeds
# with a 95% bootstrap CI. The summary and the episodes are written into the run directory.

# %%
result = pobax.evaluate(run, episodes=5 if TINY else 20, seed=0)
print(pobax.eval.format_eval(result))
print(result.episodes.head())

# %% [markdown]
# Greedy actions, and another observability of the same environment (T-Maze `full` shows the cue everywhere;
# observations must have the shape the network was trained on).

# %%
for kwargs in (dict(greedy=True), dict(observability="full")):
    s = pobax.evaluate(run, episodes=5, save=False, **kwargs).summary["sets"][run.best_set]
    print(kwargs, f"discounted return {s['disc_return']['mean']:.3f}")

# %% [markdown]
# ## Watch one episode
# An animated GIF (and a PNG strip beside it): the corridor with the cue, the agent, and the GRU's hidden state.

# %%
picture = pobax.render_episode(run, OUT / "tmaze5-episode.gif", seed=2)
ret, disc = picture.episode.returns
print(f"{picture.episode.length} steps, return {ret:.2f} (discounted {disc:.3f}) -> {picture.gif}, {picture.png}")

# %% [markdown]
# ## The network by hand
# One run's network; `policy_step` is what the rollout and the evaluation call at every step (the memory resets
# where `start` is true).

# %%
model, norm = run.pick(set=run.best_set, seed=0), run.pick_obs_norm(set=run.best_set, seed=0)
env = run.env  # the environment as trained: time limit, previous action if `action_concat`, auto-reset
state, ts = env.reset(key=jax.random.key(0))
carry, start = model.init_carry(), jnp.asarray(True)
for t in range(8):
    obs = ts.obs if norm is None else norm(ts.obs)  # runs that normalised observations keep their statistics
    carry, action, logp, value = pobax.agent.policy_step(model, carry, obs, start, jax.random.key(t), greedy=True)
    state, ts = env.step(state, action, key=jax.random.key(100 + t))
    print(f"step {t}: action {int(action)}, value {float(value[0]):.3f}, reward {float(ts.reward)}")
    start = ts.done
    if bool(ts.done):
        break
