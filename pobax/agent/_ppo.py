"""PPO (and λ-discrepancy) for memory agents: one update is a pure function of a named training state.

An update collects `num_steps` transitions from `num_envs` environments, computes GAE, then runs
`update_epochs` passes of `num_minibatches` minibatches. A minibatch holds whole environment sequences and
replays the memory from the carry saved at the start of the rollout, with the same `starts` flags the rollout
used, so the replayed network computes exactly what the rollout computed.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray, PyTree

from .._backend import Backend
from ..env import AbstractEnvironment, DictSpace, observation_array
from ..memory import with_matmul_batch
from ..memory._layers import NO_BATCH
from ._config import Hyperparams, TrainConfig
from ._gae import gae
from ._network import ActorCritic, memory_options, release_init


class EpisodeStats(eqx.Module):
    """Running statistics of the episode each environment is in: its return, discounted return (Σ γ^t r_t), the
    discount of its next reward (γ^t) and its length. Training and evaluation account episodes with it."""

    ret: Float[Array, " envs"]
    disc_ret: Float[Array, " envs"]
    discount: Float[Array, " envs"]
    length: Float[Array, " envs"]

    @staticmethod
    def zeros(num_envs: int) -> "EpisodeStats":
        z = jnp.zeros((num_envs,), jnp.float32)
        return EpisodeStats(z, z, jnp.ones((num_envs,), jnp.float32), z)

    def add(self, reward: Float[Array, " envs"], gamma, live: Bool[Array, " envs"] | None = None) -> "EpisodeStats":
        """The statistics after one more step with `reward`; where `live` is false (an episode already over, which
        evaluation keeps as it ended) nothing changes."""
        if live is None:
            return EpisodeStats(self.ret + reward, self.disc_ret + self.discount * reward, self.discount * gamma,
                                self.length + 1.0)
        reward = jnp.where(live, reward, 0.0)
        return EpisodeStats(self.ret + reward, self.disc_ret + self.discount * reward,
                            jnp.where(live, self.discount * gamma, self.discount), self.length + live)

    def restart(self, done: Bool[Array, " envs"]) -> "EpisodeStats":
        """Fresh statistics where `done` (the environment started a new episode), these elsewhere."""
        keep = 1.0 - done.astype(jnp.float32)
        return EpisodeStats(self.ret * keep, self.disc_ret * keep, jnp.where(done, 1.0, self.discount),
                            self.length * keep)


class ObsNorm(eqx.Module):
    """Running mean and variance of the observations of one run (all its environments), for normalisation.

    Updated with each rollout step's batch of observations before the agent sees them (Chan et al.'s parallel
    update), so the statistics are those of every observation the run has acted on. The normalised observation
    is `clip((x − mean) / sqrt(var + 1e-8), −10, 10)`; the rollout stores normalised observations, so the PPO
    replay sees exactly what the rollout saw.
    """

    mean: Float[Array, "*obs"]
    var: Float[Array, "*obs"]
    count: Float[Array, ""]

    @staticmethod
    def init(shape: tuple[int, ...]) -> "ObsNorm":
        # a tiny prior count keeps the first update well defined (its weight vanishes after one batch)
        return ObsNorm(jnp.zeros(shape, jnp.float32), jnp.ones(shape, jnp.float32), jnp.asarray(1e-4, jnp.float32))

    def update(self, batch: Float[Array, "n *obs"]) -> "ObsNorm":
        batch = batch.astype(jnp.float32)
        n = jnp.asarray(batch.shape[0], jnp.float32)
        b_mean, b_var = batch.mean(axis=0), batch.var(axis=0)
        total = self.count + n
        delta = b_mean - self.mean
        mean = self.mean + delta * (n / total)
        m2 = self.var * self.count + b_var * n + delta**2 * (self.count * n / total)
        return ObsNorm(mean, m2 / total, total)

    def __call__(self, obs: PyTree[Array]) -> PyTree[Array]:
        """Normalise an observation (or a batch of them); an action mask travels unchanged."""
        x = observation_array(obs).astype(jnp.float32)
        lead = (1,) * (x.ndim - self.mean.ndim)
        mean, var = self.mean.reshape(lead + self.mean.shape), self.var.reshape(lead + self.var.shape)
        y = jnp.clip((x - mean) / jnp.sqrt(var + 1e-8), -10.0, 10.0)
        return {**obs, "obs": y} if isinstance(obs, dict) else y


class RewardNorm(eqx.Module):
    """Reward scaling by the running standard deviation of each environment's discounted return.

    Each step, `ret ← γ·ret + r` per environment (reset to 0 after an episode ends), the running variance of
    `ret` over all steps and environments is updated, and the reward given to GAE is `r / sqrt(var + 1e-8)`.
    The scale is one positive number shared by all environments that changes slowly as statistics accumulate,
    so the advantages' signs and the greedy policy are those of the raw rewards; logged returns are computed
    from the raw rewards.
    """

    ret: Float[Array, " envs"]
    stats: ObsNorm

    @staticmethod
    def init(num_envs: int) -> "RewardNorm":
        return RewardNorm(jnp.zeros((num_envs,), jnp.float32), ObsNorm.init(()))

    def __call__(self, reward: Float[Array, " envs"], done: Bool[Array, " envs"], gamma: float):
        ret = self.ret * gamma + reward
        stats = self.stats.update(ret)
        scaled = reward / jnp.sqrt(stats.var + 1e-8)
        return RewardNorm(jnp.where(done, 0.0, ret), stats), scaled


def obs_normalizable(env: AbstractEnvironment) -> bool:
    """Observation normalisation applies to vector observations (images are scaled by the encoder): `Runs` refuses
    `normalize_obs` for images; `init_state` and loading still skip it there for run directories written before."""
    space = env.observation_space
    space = space["obs"] if isinstance(space, DictSpace) else space
    return len(space.shape) <= 1


class TrainState(eqx.Module):
    """Everything a run needs to continue: a checkpoint is exactly this."""

    model: ActorCritic
    opt_state: PyTree
    env_state: PyTree
    obs: PyTree[Array]
    starts: Bool[Array, " envs"]
    carry: PyTree
    episode: EpisodeStats
    key: PRNGKeyArray
    update: Int[Array, ""]
    obs_norm: ObsNorm | None = None
    reward_norm: RewardNorm | None = None


def _optimizer() -> optax.GradientTransformation:
    # Clipping and the (annealed, per-run) step size are applied by hand so that both can be vmapped.
    return optax.scale_by_adam(eps=1e-5)


def make_model(cfg: TrainConfig, env: AbstractEnvironment, key: PRNGKeyArray,
               backend: Backend = Backend()) -> ActorCritic:
    """The network of `cfg` for `env`, with the implementation choices of `backend` (default: the CPU's, which run
    on every platform; `Runs` passes its devices')."""
    model = ActorCritic(
        env, key=key, memory=cfg.memory, hidden_size=cfg.hidden_size, encoder=cfg.encoder,
        num_critics=2 if cfg.double_critic else 1, **memory_options(cfg, backend),
    )
    return release_init(model) if cfg.init == "release" else model


def init_state(cfg: TrainConfig, env: AbstractEnvironment, key: PRNGKeyArray,
               backend: Backend = Backend()) -> TrainState:
    """The initial training state of one run (`backend`: as `make_model`'s)."""
    k_model, k_env, k_run = jax.random.split(key, 3)
    model = make_model(cfg, env, k_model, backend)
    env_state, ts = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(k_env, cfg.num_envs))
    carry = jax.vmap(lambda _: model.init_carry())(jnp.arange(cfg.num_envs))
    obs_norm = None
    if cfg.normalize_obs and obs_normalizable(env):
        obs_norm = ObsNorm.init(observation_array(ts.obs).shape[1:])
    return TrainState(
        model=model,
        opt_state=_optimizer().init(eqx.filter(model, eqx.is_inexact_array)),
        env_state=env_state,
        obs=ts.obs,
        starts=jnp.ones((cfg.num_envs,), bool),
        carry=carry,
        episode=EpisodeStats.zeros(cfg.num_envs),
        key=k_run,
        update=jnp.zeros((), jnp.int32),
        obs_norm=obs_norm,
        reward_norm=RewardNorm.init(cfg.num_envs) if cfg.normalize_reward else None,
    )


def _first(x):
    return jax.tree.map(lambda a: a[None], x)


def policy_step(model: ActorCritic, carry: PyTree, obs: PyTree[Array], start: Bool[Array, ""], key: PRNGKeyArray,
                greedy: bool = False):
    """One step of the policy in one environment, as the rollout takes it: the network on a sequence of length 1
    (the memory resets first when `start`), then an action sampled from the policy (its mode when `greedy`).
    Returns `(carry, action, log-probability of the action, values (critics,))`. Evaluation calls this; the rollout
    computes the same in one call with the step before's bootstrap value (`_policy_and_bootstrap`), so a trained
    agent acts as it did in training. `start` is one flag (a bool); a model stacked over runs (`load_run`'s), or a
    batch of observations, is refused with a ValueError saying so: `jax.vmap` this for a batch."""
    start = jnp.asarray(start)
    if start.shape != () or start.dtype != bool:
        raise ValueError(f"policy_step: start is one flag (a bool of shape ()), got {start.dtype} of shape "
                         f"{start.shape}; jax.vmap policy_step for a batch of environments.")
    try:
        carry, dist, values = model(carry, _first(obs), start[None])
    except (TypeError, ValueError) as e:
        raise ValueError(f"policy_step: the model, carry and observation do not fit together "
                         f"({str(e).splitlines()[0][:200]}): pass one run's model (LoadedRun.pick(set=, seed=)), its "
                         f"init_carry() and one environment's observation; jax.vmap policy_step for a batch.") from e
    return (carry, *_act(dist, values, key, greedy))


def _act(dist, values, key, greedy: bool = False):
    action = dist.mode() if greedy else dist.sample(key)
    return action[0], dist.log_prob(action)[0], values[0]


def _policy_and_bootstrap(model: ActorCritic, carry: PyTree, obs: PyTree[Array], start: Bool[Array, ""],
                          prev_final_obs: PyTree[Array], key: PRNGKeyArray):
    """`policy_step` on `obs`, and in the same call of the network the values of `prev_final_obs` (the observation
    that followed the step before, within its episode) from the same carry without a reset: the bootstrap value of
    the step before. Both inputs read the carry the step before left, so one call on a batch of two replaces two
    calls (the rollout's time loop is bound by its number of kernels, not their size)."""
    both = jax.tree.map(lambda a, b: jnp.stack([a, b])[:, None], obs, prev_final_obs)  # (2, time 1, ...)
    starts = jnp.stack([start, jnp.zeros_like(start)])[:, None]
    carries, dists, values = jax.vmap(model, in_axes=(None, 0, 0))(carry, both, starts)
    own = lambda tree: jax.tree.map(lambda a: a[0], tree)  # noqa: E731
    return (own(carries), *_act(own(dists), values[0], key), values[1, 0])


def rollout_rows(runs: int, num_envs: int) -> int:
    """The rows a dense layer of the rollout's network call has once the `vmap`s around it apply (the `rows` of
    `pobax.memory.with_matmul_batch`): two inputs (the step's observation and the step before's final one,
    `_policy_and_bootstrap`) per environment of each of `runs` runs."""
    return 2 * runs * num_envs


def rollout(cfg: TrainConfig, env: AbstractEnvironment, state: TrainState, matmul_batch: tuple[int, int] = NO_BATCH):
    """Collect `num_steps` transitions from every environment. Returns the new state and a trajectory
    dict of arrays with leading axes (time, envs). `matmul_batch`: the network's layers' (`rows`, `limit`) in this
    program (`pobax.memory.with_matmul_batch`; `update` passes it).

    `next_values[t]`, the value of the observation that followed step t within its episode (the final observation
    of an episode that ended: a truncated one bootstraps from it), comes from the same network call as step t + 1's
    action (`_policy_and_bootstrap`: both read the carry step t left, the final observation without a reset); the
    last step's from one more call after the loop."""
    model = with_matmul_batch(state.model, *matmul_batch) if matmul_batch != NO_BATCH else state.model
    gamma = env.gamma

    def step(carry_in, _):
        s, prev_final_obs = carry_in
        # One split gives the step's keys: the run's next key, then one per environment for the action, then one
        # per environment for its step.
        keys = jax.random.split(s.key, 1 + 2 * cfg.num_envs)
        key, k_acts, k_envs = keys[0], keys[1:1 + cfg.num_envs], keys[1 + cfg.num_envs:]
        obs, obs_norm = s.obs, s.obs_norm
        if obs_norm is not None:
            obs_norm = obs_norm.update(observation_array(obs))
            obs = obs_norm(obs)
        carry, action, logp, values, prev_next_values = jax.vmap(functools.partial(_policy_and_bootstrap, model))(
            s.carry, obs, s.starts, prev_final_obs, k_acts)
        env_state, ts = jax.vmap(lambda es, a, k: env.step(es, a, key=k))(s.env_state, action, k_envs)
        final_obs = ts.obs if ts.final_obs is None else ts.final_obs
        if obs_norm is not None:
            final_obs = obs_norm(final_obs)
        done = ts.done
        reward, reward_norm = ts.reward, s.reward_norm
        if cfg.reward_scale != 1.0:
            reward = reward * cfg.reward_scale
        if reward_norm is not None:
            reward_norm, reward = reward_norm(reward, done, gamma)
        ep = s.episode.add(ts.reward, gamma)
        trans = dict(
            obs=obs, starts=s.starts, action=action, logp=logp, values=values, prev_next_values=prev_next_values,
            reward=reward, terminated=ts.terminated, truncated=ts.truncated,
            ep_done=done, ep_return=ep.ret, ep_disc_return=ep.disc_ret, ep_length=ep.length,
            ep_info={k: jnp.reshape(ts.info[k], (cfg.num_envs, -1)) for k in env.episode_metrics},
        )
        episode = ep.restart(done)
        s = TrainState(
            model=s.model, opt_state=s.opt_state, env_state=env_state, obs=ts.obs, starts=done, carry=carry,
            episode=episode, key=key, update=s.update, obs_norm=obs_norm, reward_norm=reward_norm,
        )
        return (s, final_obs), trans

    # The first step's "observation before" is a stand-in of the right shape: its value is not used.
    first_obs = state.obs if state.obs_norm is None else state.obs_norm(state.obs)
    (state, last_final_obs), traj = jax.lax.scan(step, (state, first_obs), None, length=cfg.num_steps,
                                                 unroll=cfg.rollout_unroll)

    def last_value(carry, final_obs):
        _, _, values = model(carry, _first(final_obs), jnp.zeros((1,), bool))
        return values[0]

    last = jax.vmap(last_value)(state.carry, last_final_obs)
    traj["next_values"] = jnp.concatenate([traj.pop("prev_next_values")[1:], last[None]])
    return state, traj


def ppo_loss(model: ActorCritic, mb: dict, hp: Hyperparams, double_critic: bool,
             matmul_batch: tuple[int, int] = NO_BATCH, normalize_advantages: bool = True):
    """Clipped PPO loss on a minibatch of whole sequences (arrays with leading axes (time, envs)); `matmul_batch`:
    as `rollout`'s; `normalize_advantages`: the minibatch's advantages standardised first."""
    if matmul_batch != NO_BATCH:
        model = with_matmul_batch(model, *matmul_batch)
    _, dist, values = jax.vmap(model, in_axes=(0, 1, 1), out_axes=(0, 1, 1))(mb["carry"], mb["obs"], mb["starts"])
    logp = dist.log_prob(mb["action"])
    log_ratio = logp - mb["logp"]
    ratio = jnp.exp(log_ratio)
    adv = mb["advantages"]
    if normalize_advantages:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    pg_loss = -jnp.minimum(ratio * adv, jnp.clip(ratio, 1.0 - hp.clip_eps, 1.0 + hp.clip_eps) * adv).mean()

    old_v, targets = mb["values"], mb["targets"]
    v_clipped = old_v + jnp.clip(values - old_v, -hp.clip_eps, hp.clip_eps)
    v_losses = 0.5 * jnp.maximum((values - targets) ** 2, (v_clipped - targets) ** 2).mean(axis=(0, 1))
    if double_critic:
        discrepancy = jnp.mean((values[..., 0] - values[..., 1]) ** 2)
        v_loss = (1.0 - hp.ld_weight) * v_losses.sum() + hp.ld_weight * discrepancy
    else:
        v_loss = v_losses[0]
    entropy = dist.entropy().mean()
    total = pg_loss + hp.vf_coeff * v_loss - hp.entropy_coeff * entropy
    stats = dict(
        pg_loss=pg_loss, v_loss=v_loss, entropy=entropy,
        approx_kl=((ratio - 1.0) - log_ratio).mean(),
        clip_frac=(jnp.abs(ratio - 1.0) > hp.clip_eps).mean(),
    )
    return total, stats


def update(cfg: TrainConfig, env: AbstractEnvironment, state: TrainState, hp: Hyperparams,
           matmul_batch: tuple[int, int] = NO_BATCH, gae_method: str = "auto"):
    """One PPO update (rollout, GAE, epochs of minibatch SGD). Returns the new state and scalar metrics.
    `matmul_batch`: `(rows, limit)` of the network's layers in this program (`pobax.memory.with_matmul_batch`: the
    training loop passes `rollout_rows` of its runs and the backend's bound); `gae_method`: `gae`'s (the backend's)."""
    init_carry = state.carry
    state, traj = rollout(cfg, env, state, matmul_batch)

    gamma = env.gamma
    v, nv = traj["values"], traj["next_values"]
    adv0, tgt0 = gae(traj["reward"], v[..., 0], nv[..., 0], traj["terminated"], traj["truncated"], gamma, hp.lambda0,
                     method=gae_method)
    if cfg.double_critic:
        adv1, tgt1 = gae(traj["reward"], v[..., 1], nv[..., 1], traj["terminated"], traj["truncated"], gamma,
                         hp.lambda1, method=gae_method)
        advantages = hp.alpha * adv0 + (1.0 - hp.alpha) * adv1
        targets = jnp.stack([tgt0, tgt1], axis=-1)
    else:
        advantages, targets = adv0, tgt0[..., None]

    batch = dict(
        obs=traj["obs"], starts=traj["starts"], action=traj["action"], logp=traj["logp"], values=v,
        advantages=advantages, targets=targets,
    )
    frac = 1.0 - state.update.astype(jnp.float32) / cfg.num_updates
    lr = hp.lr * frac if cfg.anneal_lr else hp.lr
    opt = _optimizer()
    mb_envs = cfg.num_envs // cfg.num_minibatches
    grad_fn = eqx.filter_value_and_grad(ppo_loss, has_aux=True)

    def minibatch(carry, idx):
        model, opt_state = carry
        mb = jax.tree.map(lambda x: x[:, idx], batch)
        mb["carry"] = jax.tree.map(lambda x: x[idx], init_carry)
        (loss, stats), grads = grad_fn(model, mb, hp, cfg.double_critic, matmul_batch, cfg.normalize_advantages)
        norm = jnp.sqrt(sum(jnp.sum(g**2) for g in jax.tree.leaves(grads)))
        # A non-finite loss or gradient makes the parameters non-finite: the run has diverged.
        stats["nonfinite"] = ~(jnp.isfinite(loss) & jnp.isfinite(norm))
        scale = jnp.where(norm > hp.max_grad_norm, hp.max_grad_norm / norm, 1.0)
        updates, opt_state = opt.update(jax.tree.map(lambda g: g * scale, grads), opt_state)
        model = eqx.apply_updates(model, jax.tree.map(lambda u: -lr * u, updates))
        return (model, opt_state), stats

    def epoch(carry, key):
        perm = jax.random.permutation(key, cfg.num_envs).reshape(cfg.num_minibatches, mb_envs)
        return jax.lax.scan(minibatch, carry, perm)

    key, k_epochs = jax.random.split(state.key)
    (model, opt_state), stats = jax.lax.scan(
        epoch, (state.model, state.opt_state), jax.random.split(k_epochs, cfg.update_epochs)
    )
    done = traj["ep_done"].astype(jnp.float32)
    metrics = {k: x.mean() for k, x in stats.items() if k != "nonfinite"}
    metrics["nonfinite"] = jnp.any(stats["nonfinite"]).astype(jnp.float32)
    metrics.update(
        episodes=done.sum(),
        return_sum=(done * traj["ep_return"]).sum(),
        disc_return_sum=(done * traj["ep_disc_return"]).sum(),
        length_sum=(done * traj["ep_length"]).sum(),
        lr=lr,
        value_mean=v[..., 0].mean(),
    )
    for k, names in env.episode_metrics.items():  # per-episode info at episode ends, e.g. achievements
        sums = jnp.sum(done[..., None] * traj["ep_info"][k].astype(jnp.float32), axis=(0, 1))
        metrics.update({f"episode/{name}": sums[i] for i, name in enumerate(names)})
    if cfg.double_critic:
        metrics["lambda_discrepancy"] = jnp.mean((v[..., 0] - v[..., 1]) ** 2)
    state = TrainState(
        model=model, opt_state=opt_state, env_state=state.env_state, obs=state.obs, starts=state.starts,
        carry=state.carry, episode=state.episode, key=key, update=state.update + 1, obs_norm=state.obs_norm,
        reward_norm=state.reward_norm,
    )
    return state, metrics
