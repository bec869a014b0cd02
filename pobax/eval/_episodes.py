"""Playing episodes with a trained agent: `record_episode` (one episode step by step, for `render`) and the
vmapped episodes `evaluate` measures.

The policy acts as in training: `pobax.agent.policy_step` on one observation at a time, the memory reset before
the first observation of each episode (its `starts` flag), the observation normalised by the run's statistics
(frozen). Episode i of seed s starts from the key `fold_in(key(s), i)`, the same for every run of the directory
(common random numbers: every run plays the same worlds), so results are deterministic for a seed.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._backend import compiler_options
from ..agent import EpisodeStats, make_env, policy_step
from ..agent._config import INT32_MAX
from ..env import AutoReset, DictSpace, TimeLimitState, spec
from ..env._base import check_seed
from ..env._wrappers import tree_select
from ..memory import TrXLCarry
from ._load import LoadedRun, missing_obs_norm


class EvalError(ValueError):
    """Evaluation settings that cannot be honoured (e.g. an observability the network cannot read)."""


def _obs_shape(space) -> tuple:
    return tuple((space["obs"] if isinstance(space, DictSpace) else space).shape)


def episode_env(run: LoadedRun, observability: str | None = None):
    """The environment to play fresh episodes in: the run's (or another `observability` of the same environment,
    which must give observations of the shape the network was trained on), with its time limit and without
    auto-reset."""
    cfg = run.config
    obs = cfg.observability if observability is None else observability
    given, trained = run.trained_env
    if trained == "given" and obs != cfg.observability:  # make_env would build cfg.env's, not the one it trained in
        raise EvalError(f"{str(run.path)!r} trained in an environment given to train(env=...) ({given}): another "
                        f"observability ({obs!r}) would play {cfg.env}'s registered one; play it without one.")
    env = run.env if obs == cfg.observability else make_env(cfg, obs)
    want, got = _obs_shape(run.env.observation_space), _obs_shape(env.observation_space)
    if got != want or isinstance(env.observation_space, DictSpace) != isinstance(run.env.observation_space, DictSpace):
        same = [o for o in spec(cfg.env).observabilities
                if _obs_shape(make_env(cfg, o).observation_space) == want]
        raise EvalError(f"Observability {obs!r} of {cfg.env} gives observations of shape {got}, but the network was "
                        f"trained on {cfg.observability!r} observations of shape {want}; choose one of: "
                        f"{', '.join(same)}.")
    return env.env if isinstance(env, AutoReset) else env


def memory_trace(carry):
    """A real vector of the memory's state, for pictures: every floating-point leaf of the carry, flattened, complex
    ones (a user's cell may have them) as their real then imaginary parts; of a Transformer-XL's cache, the newest
    cached input of its last layer. None without a memory."""
    if isinstance(carry, TrXLCarry):
        carry = carry.memory[-1, -1]
    leaves = []
    for x in jax.tree.leaves(carry):
        if jnp.issubdtype(x.dtype, jnp.complexfloating):
            leaves += [x.real.reshape(-1), x.imag.reshape(-1)]
        elif jnp.issubdtype(x.dtype, jnp.floating):
            leaves.append(x.reshape(-1))
    return jnp.concatenate(leaves).astype(jnp.float32) if leaves else None


def check_obs_norm(run: LoadedRun) -> None:
    if missing_obs_norm(run):
        raise EvalError("The run normalised its observations, but its statistics were not saved with the model (a "
                        "run finished before obs_norm.eqx existed): its network cannot be given the inputs it "
                        "learned on.")


def _raw_state(state):
    while isinstance(state, TimeLimitState):
        state = state.env_state
    return state


def _act(model, obs_norm, env, state, obs, carry, start, key, t, greedy):
    """One step of one environment: the policy (as in training), then the environment."""
    k_act, k_env = jax.random.split(jax.random.fold_in(key, t))
    x = obs if obs_norm is None else obs_norm(obs)
    carry, action, _, values = policy_step(model, carry, x, start, k_act, greedy)
    new_state, ts = env.step(state, action, key=k_env)
    return carry, action, values, new_state, ts


def play_episodes(model, obs_norm, env, keys, greedy: bool, max_steps: int):
    """One episode per key (vmapped) until every one has ended or `max_steps` steps."""
    n = keys.shape[0]
    k_reset, k_steps = jax.vmap(lambda k: tuple(jax.random.split(k)))(keys)
    state, ts = jax.vmap(lambda k: env.reset(key=k))(k_reset)
    carry = jax.vmap(lambda _: model.init_carry())(jnp.arange(n))
    false = jnp.zeros((n,), bool)
    metrics = {k: jnp.zeros((n, len(names)), jnp.float32) for k, names in env.episode_metrics.items()}
    ep = EpisodeStats.zeros(n)
    stats = dict(ret=ep.ret, disc_ret=ep.disc_ret, discount=ep.discount, length=ep.length, terminated=false,
                 truncated=false, done=false, metrics=metrics)
    act = jax.vmap(_act, in_axes=(None, None, None, 0, 0, 0, 0, 0, None, None))

    def body(c):
        state, obs, carry, start, s, t = c
        carry, _, _, new_state, ts = act(model, obs_norm, env, state, obs, carry, start, k_steps, t, greedy)
        live = ~s["done"]
        ep = EpisodeStats(s["ret"], s["disc_ret"], s["discount"], s["length"]).add(ts.reward, env.gamma, live)
        info = {k: jnp.reshape(ts.info[k], (n, -1)).astype(jnp.float32) for k in s["metrics"]}
        s = dict(ret=ep.ret, disc_ret=ep.disc_ret, discount=ep.discount,
                 length=ep.length, terminated=s["terminated"] | (live & ts.terminated),
                 truncated=s["truncated"] | (live & ts.truncated), done=s["done"] | (live & ts.done),
                 metrics={k: jnp.where(live[:, None], info[k], m) for k, m in s["metrics"].items()})
        state = jax.vmap(tree_select)(live, new_state, state)
        obs = jax.vmap(tree_select)(live, ts.obs, obs)
        return state, obs, carry, jnp.zeros_like(start), s, t + 1

    def cond(c):
        return (c[5] < max_steps) & ~jnp.all(c[4]["done"])

    c = jax.lax.while_loop(cond, body, (state, ts.obs, carry, jnp.ones((n,), bool), stats, jnp.zeros((), jnp.int32)))
    return c[4]


def jit_for(fn, cfg):
    """`fn` compiled with the run configuration's compiler options (deterministic, fast compile)."""
    return eqx.filter_jit(fn, compiler_options=compiler_options(cfg.deterministic, cfg.fast_compile) or None)


def episode_keys(seed: int, episodes: int):
    """Episode i's key for a seed: `fold_in(key(seed), i)`, the same for every run."""
    check_seed(seed)
    return jax.vmap(lambda i: jax.random.fold_in(jax.random.key(seed), i))(jnp.arange(episodes))


def check_count(flag: str, v) -> int:
    """`v` as a count of at least 1 that the program can count (int32), else an EvalError naming `flag`."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not 1 <= v <= INT32_MAX:
        raise EvalError(f"{flag} must be a positive integer of at most {INT32_MAX:,} (the program counts in int32), "
                        f"got {v!r}.")
    return int(v)


def episode_limit(env, max_steps: int | None) -> int:
    """The steps an episode may last: `max_steps`, else the environment's time limit (else 10,000)."""
    if max_steps is not None:  # the step counter of `play_episodes`'s loop is int32
        return check_count("--max-steps", max_steps)
    return int(env.max_steps_in_episode or 10_000)


@dataclasses.dataclass
class Episode:
    """One recorded episode (`record_episode`): `views[t]` what the environment's drawer needs of the state before
    action t (and, last, of the final state: T + 1 entries), `actions`, `rewards`, `values` (critics) per step,
    `memory` (T, units) the memory's state after each step (None without a memory), how it ended."""

    views: object
    actions: np.ndarray
    rewards: np.ndarray
    values: np.ndarray
    memory: np.ndarray | None
    terminated: bool
    truncated: bool
    gamma: float

    @property
    def length(self) -> int:
        """Steps played."""
        return len(self.actions)

    @property
    def returns(self) -> tuple[float, float]:
        """(undiscounted, discounted) return."""
        return float(self.rewards.sum()), float(np.sum(self.rewards * self.gamma ** np.arange(self.length)))


#: Steps `record_episode` plays per program call: an episode is played in blocks until it ends, so that its work and
#: memory follow the episode's length, not `max_steps` (a 22-step episode under --steps 20,000,000 took 2 GB).
RECORD_BLOCK = 1024


def record_episode(run: LoadedRun, capture, *, env=None, index: int = 0, seed: int = 0, greedy: bool = False,
                   max_steps: int = 200) -> Episode:
    """Play one episode (episode 0 of `evaluate` with the same seed) with run `index` of `run` in `env` (default:
    `episode_env(run)`), keeping what `capture(raw_env, raw_state, obs)` takes of each state, the actions, rewards,
    values and the memory's state. It is played `RECORD_BLOCK` steps at a time until it ends or `max_steps` steps."""
    check_obs_norm(run)
    env = episode_env(run) if env is None else env
    model, obs_norm = run.pick(index=index), run.pick_obs_norm(index=index)
    limit = min(check_count("--steps", max_steps), episode_limit(env, None))
    raw_env = env.unwrapped
    block = min(limit, RECORD_BLOCK)

    def begin(model, env, key):
        k_reset, k_steps = jax.random.split(key)
        state, ts = env.reset(key=k_reset)
        return (state, ts.obs, model.init_carry(), jnp.asarray(True), jnp.asarray(False)), k_steps

    def go(model, obs_norm, env, k_steps, c0, t0):
        def body(c, t):
            state, obs, carry, start, done = c
            done = done | (t >= limit)  # past max_steps in the last block: held where it stopped, nothing recorded
            view = capture(raw_env, _raw_state(state), obs)
            carry, action, values, new_state, ts = _act(model, obs_norm, env, state, obs, carry, start, k_steps, t,
                                                        greedy)
            rec = dict(view=view, action=action, reward=jnp.where(done, 0.0, ts.reward), values=values,
                       memory=memory_trace(carry), ended=~done & ts.done, terminated=~done & ts.terminated)
            c = (tree_select(done, state, new_state), tree_select(done, obs, ts.obs), carry, jnp.asarray(False),
                 done | ts.done)
            return c, rec

        c, recs = jax.lax.scan(body, c0, t0 + jnp.arange(block))
        return c, recs, capture(raw_env, _raw_state(c[0]), c[1])

    c, k_steps = jit_for(begin, run.config)(model, env, episode_keys(seed, 1)[0])
    play, blocks, t0 = jit_for(go, run.config), [], 0
    while True:
        c, recs, last = play(model, obs_norm, env, k_steps, c, jnp.asarray(t0))
        blocks.append(jax.device_get(recs))
        t0 += block
        if t0 >= limit or bool(c[4]):
            break
    recs = jax.tree.map(lambda *b: np.concatenate(b)[:limit], *blocks)
    last = jax.device_get(last)
    ended = np.flatnonzero(recs["ended"])
    t = int(ended[0]) + 1 if len(ended) else limit
    views = jax.tree.map(lambda v, l: np.concatenate([np.asarray(v)[:t], np.asarray(l)[None]]), recs["view"], last)
    memory = None if recs["memory"] is None else np.asarray(recs["memory"])[:t]
    return Episode(views, np.asarray(recs["action"])[:t], np.asarray(recs["reward"])[:t],
                   np.asarray(recs["values"])[:t], memory, bool(recs["terminated"][:t].any()),
                   bool(len(ended) and not recs["terminated"][:t].any()), float(env.gamma))
