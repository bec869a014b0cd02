"""PPO (and λ-discrepancy) for memory agents: one update is a pure function of a named training state.

An update collects `num_steps` transitions from `num_envs` environments, computes GAE, then runs
`update_epochs` passes of `num_minibatches` minibatches. A minibatch holds whole environment sequences and
replays the memory from the carry saved at the start of the rollout, with the same `starts` flags the rollout
used, so the replayed network computes exactly what the rollout computed.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray, PyTree

from ..env import AbstractEnvironment, DictSpace, observation_array
from ._config import Hyperparams, TrainConfig
from ._gae import gae
from ._network import ActorCritic


class EpisodeStats(eqx.Module):
    """Running statistics of the episode each environment is in."""

    ret: Float[Array, " envs"]
    disc_ret: Float[Array, " envs"]
    discount: Float[Array, " envs"]
    length: Float[Array, " envs"]

    @staticmethod
    def zeros(num_envs: int) -> "EpisodeStats":
        z = jnp.zeros((num_envs,), jnp.float32)
        return EpisodeStats(z, z, jnp.ones((num_envs,), jnp.float32), z)


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


def make_model(cfg: TrainConfig, env: AbstractEnvironment, key: PRNGKeyArray) -> ActorCritic:
    return ActorCritic(
        env, key=key, memory=cfg.memory, hidden_size=cfg.hidden_size, encoder=cfg.encoder,
        num_critics=2 if cfg.double_critic else 1, **cfg.memory_kwargs(),
    )


def init_state(cfg: TrainConfig, env: AbstractEnvironment, key: PRNGKeyArray) -> TrainState:
    """The initial training state of one run."""
    k_model, k_env, k_run = jax.random.split(key, 3)
    model = make_model(cfg, env, k_model)
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
    Returns `(carry, action, log-probability of the action, values (critics,))`. Evaluation calls this too, so a
    trained agent acts exactly as it did in training."""
    carry, dist, values = model(carry, _first(obs), start[None])
    action = dist.mode() if greedy else dist.sample(key)
    return carry, action[0], dist.log_prob(action)[0], values[0]


def rollout(cfg: TrainConfig, env: AbstractEnvironment, state: TrainState):
    """Collect `num_steps` transitions from every environment. Returns the new state and a trajectory
    dict of arrays with leading axes (time, envs)."""
    model = state.model
    gamma = env.gamma

    def act(carry, obs, start, key):
        return policy_step(model, carry, obs, start, key)

    def final_value(carry, final_obs):
        # Value of the observation that followed this step in the same episode (the final observation of an
        # episode that just ended): the memory continues from its carry, without a reset.
        _, _, values = model(carry, _first(final_obs), jnp.zeros((1,), bool))
        return values[0]

    def step(s: TrainState, _):
        # One split gives the step's keys: the run's next key, then one per environment for the action, then one
        # per environment for its step.
        keys = jax.random.split(s.key, 1 + 2 * cfg.num_envs)
        key, k_acts, k_envs = keys[0], keys[1:1 + cfg.num_envs], keys[1 + cfg.num_envs:]
        obs, obs_norm = s.obs, s.obs_norm
        if obs_norm is not None:
            obs_norm = obs_norm.update(observation_array(obs))
            obs = obs_norm(obs)
        carry, action, logp, values = jax.vmap(act)(s.carry, obs, s.starts, k_acts)
        env_state, ts = jax.vmap(lambda es, a, k: env.step(es, a, key=k))(s.env_state, action, k_envs)
        final_obs = ts.obs if ts.final_obs is None else ts.final_obs
        if obs_norm is not None:
            final_obs = obs_norm(final_obs)
        next_values = jax.vmap(final_value)(carry, final_obs)
        done = ts.done
        reward, reward_norm = ts.reward, s.reward_norm
        if reward_norm is not None:
            reward_norm, reward = reward_norm(ts.reward, done, gamma)
        ep = s.episode
        ret = ep.ret + ts.reward
        disc_ret = ep.disc_ret + ep.discount * ts.reward
        length = ep.length + 1.0
        trans = dict(
            obs=obs, starts=s.starts, action=action, logp=logp, values=values, next_values=next_values,
            reward=reward, terminated=ts.terminated, truncated=ts.truncated,
            ep_done=done, ep_return=ret, ep_disc_return=disc_ret, ep_length=length,
            ep_info={k: jnp.reshape(ts.info[k], (cfg.num_envs, -1)) for k in env.episode_metrics},
        )
        keep = 1.0 - done.astype(jnp.float32)
        episode = EpisodeStats(ret * keep, disc_ret * keep, jnp.where(done, 1.0, ep.discount * gamma), length * keep)
        s = TrainState(
            model=s.model, opt_state=s.opt_state, env_state=env_state, obs=ts.obs, starts=done, carry=carry,
            episode=episode, key=key, update=s.update, obs_norm=obs_norm, reward_norm=reward_norm,
        )
        return s, trans

    return jax.lax.scan(step, state, None, length=cfg.num_steps, unroll=cfg.rollout_unroll)


def ppo_loss(model: ActorCritic, mb: dict, hp: Hyperparams, double_critic: bool):
    """Clipped PPO loss on a minibatch of whole sequences (arrays with leading axes (time, envs))."""
    _, dist, values = jax.vmap(model, in_axes=(0, 1, 1), out_axes=(0, 1, 1))(mb["carry"], mb["obs"], mb["starts"])
    logp = dist.log_prob(mb["action"])
    log_ratio = logp - mb["logp"]
    ratio = jnp.exp(log_ratio)
    adv = mb["advantages"]
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


def update(cfg: TrainConfig, env: AbstractEnvironment, state: TrainState, hp: Hyperparams):
    """One PPO update (rollout, GAE, epochs of minibatch SGD). Returns the new state and scalar metrics."""
    init_carry = state.carry
    state, traj = rollout(cfg, env, state)

    gamma = env.gamma
    v, nv = traj["values"], traj["next_values"]
    adv0, tgt0 = gae(traj["reward"], v[..., 0], nv[..., 0], traj["terminated"], traj["truncated"], gamma, hp.lambda0)
    if cfg.double_critic:
        adv1, tgt1 = gae(traj["reward"], v[..., 1], nv[..., 1], traj["terminated"], traj["truncated"], gamma, hp.lambda1)
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
        (loss, stats), grads = grad_fn(model, mb, hp, cfg.double_critic)
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
