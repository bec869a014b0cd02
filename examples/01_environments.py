# %% [markdown]
# # Environments by hand
#
# Make an environment, step it yourself, batch it with `jax.vmap`, compare its observabilities, and look at an
# episode. Run it as a script (`python examples/01_environments.py`) or cell by cell in an editor that knows `# %%`.
# `POBAX_EXAMPLE_TINY=1` shrinks it to seconds; pictures go to `$POBAX_EXAMPLE_OUT` (default `runs/examples`).

# %%
import os
from pathlib import Path

import jax
import jax.numpy as jnp

import pobax
from pobax.agent import TrainConfig

TINY = os.environ.get("POBAX_EXAMPLE_TINY") == "1"
OUT = Path(os.environ.get("POBAX_EXAMPLE_OUT", "runs/examples"))

# %% [markdown]
# ## T-Maze by hand: the cue is seen only at the start
# Observation bits: (goal-up cue, goal-down cue, in the hallway, at the junction). Actions: 0 up, 1 right, 2 down,
# 3 left. `make` wraps the environment with its time limit and auto-reset; `wrappers=False` gives the bare one.

# %%
env = pobax.env.make("tmaze_5", wrappers=False)
state, ts = env.reset(key=jax.random.key(0))
print("goal up?", bool(state.goal_up), "first observation", ts.obs)
for action in [1] * (env.length + 1) + [0 if state.goal_up else 2]:  # walk right to the junction, turn to the goal
    state, ts = env.step(state, action, key=jax.random.key(1))
    print(f"action {action}: obs {ts.obs}, reward {float(ts.reward)}, terminated {bool(ts.terminated)}")

# %% [markdown]
# ## Observabilities: identical dynamics, different observations
# RockSample's `partial` shows a rock only on the step it is checked, `perfect_memory` keeps every reading, `full`
# shows the truth. The same key gives the same world in each.

# %%
spec = pobax.env.spec("rocksample_5_3")
print("categories:", spec.categories, "| recommended:", spec.recommended)
for obs in spec.observabilities:
    e = pobax.env.make("rocksample_5_3", obs, wrappers=False)
    s, ts = e.reset(key=jax.random.key(0))
    s, ts = e.step(s, 5, key=jax.random.key(1))  # check rock 0
    print(f"{obs:15s} rock entries after checking rock 0: {ts.obs[-3:]}")

# %% [markdown]
# ## Many environments at once
# Environments are unbatched: batch them with `jax.vmap` and compile the loop with `jax.jit`. Here a uniformly
# random legal policy plays Battleship (the observation carries the mask of cells not yet fired at).

# %%
env = pobax.env.make("battleship_6")
num_envs, steps = (8, 40) if TINY else (64, 200)


@jax.jit
def random_play(key):
    k_reset, k_run = jax.random.split(key)
    state, ts = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(k_reset, num_envs))

    def step(carry, key):
        state, obs, ret, finished = carry
        k_act, k_env = jax.random.split(key)
        logits = jnp.where(obs["action_mask"], 0.0, -jnp.inf)  # uniform over legal cells
        action = jax.random.categorical(k_act, logits)
        state, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(state, action, jax.random.split(k_env, num_envs))
        ret = ret + ts.reward
        return (state, ts.obs, jnp.where(ts.done, 0.0, ret), finished + jnp.where(ts.done, ret, 0.0)), ts.done

    init = (state, ts.obs, jnp.zeros(num_envs), jnp.zeros(num_envs))
    (_, _, _, total), done = jax.lax.scan(step, init, jax.random.split(k_run, steps))
    return total.sum() / jnp.maximum(done.sum(), 1), done.sum()


mean_return, episodes = random_play(jax.random.key(0))
print(f"random legal policy on battleship_6: {float(mean_return):.2f} over {int(episodes)} episodes")

# %% [markdown]
# ## Look at an episode
# `render_episode` draws any environment; an untrained network is enough to see the board, the shots and the
# memory's state.

# %%
run = pobax.eval.LoadedRun.untrained(TrainConfig(env="battleship_6", hidden_size=8, num_seeds=1, fast_compile=TINY))
picture = pobax.render_episode(run, OUT / "battleship_untrained.gif", max_steps=10 if TINY else 36)
print(f"{len(picture.frames)} frames -> {picture.gif}, {picture.png}")
