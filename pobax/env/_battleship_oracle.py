"""The probability-search policy for Battleship: the paper's "full state" ceiling for `battleship_{n}`.

The policy fires at the unfired cell most likely to hold a ship given every hit and miss so far (the greedy
belief policy of Berry 2011). The belief is the posterior over ship configurations: the prior is uniform over
legal configurations (as `Battleship` draws them) and an observation keeps exactly the configurations that
agree with it, so the posterior is uniform over the configurations consistent with all hits and misses.

It is represented by `num_particles` configurations (one placement index per ship) and updated by
resample-move sequential Monte Carlo:
1. *filter*: after a shot, the particles that disagree with its outcome are dropped. Particles drawn from the
   posterior before the shot and kept when they agree with it are exact draws from the posterior after it;
2. *resample*: each dropped particle is replaced by a copy of a random surviving one;
3. *move*: `sweeps` systematic-scan Gibbs sweeps. Each ship in turn is redrawn uniformly among its placements
   that overlap no other ship and no miss and cover every hit the other ships leave uncovered; this keeps the
   posterior invariant and spreads the copies out again.
Single-ship moves cannot reassign a hit from one ship to another, so the relative weight of such
assignments is carried by the filter alone; the tests compare the marginals with exact enumeration. If no
particle survives a shot (the particles gave its outcome probability ~0), they are kept, inconsistent, and
the event is counted in `BeliefState.collapses`; the benchmark reports how often that happens.

Ship placements are bitmasks of `ceil(n² / 32)` uint32 words, so every legality test is a few ANDs.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray, UInt32

from ._battleship import Battleship, bit_index, placement_tables, sample_placements


class BeliefState(eqx.Module):
    particles: Int[Array, "particles ships"]  # placement index of each ship, per particle
    hits: UInt32[Array, " words"]  # bitmask of cells fired at and hit
    misses: UInt32[Array, " words"]
    fired: Bool[Array, " cells"]
    collapses: Int[Array, ""]  # shots after which no particle was consistent


class ProbabilitySearch(eqx.Module):
    """Greedy posterior-marginal search for `Battleship(size, ship_lengths)`."""

    size: int = eqx.field(static=True, default=10)
    ship_lengths: tuple[int, ...] = eqx.field(static=True, default=(5, 4, 3, 2))
    num_particles: int = eqx.field(static=True, default=256)
    sweeps: int = eqx.field(static=True, default=2)

    def __check_init__(self):
        if self.num_particles < 1 or self.sweeps < 0:
            raise ValueError(
                f"ProbabilitySearch needs num_particles >= 1 and sweeps >= 0; got {self.num_particles}, "
                f"{self.sweeps}."
            )

    @property
    def num_cells(self) -> int:
        return self.size * self.size

    def _masks(self) -> list[Array]:
        return [jnp.asarray(placement_tables(self.size, length)[1]) for length in self.ship_lengths]

    def init(self, *, key: PRNGKeyArray) -> BeliefState:
        """The prior: independent draws of legal configurations."""
        keys = jax.random.split(key, self.num_particles)
        particles = jax.vmap(lambda k: sample_placements(k, self.size, self.ship_lengths))(keys)
        words = (self.num_cells + 31) // 32
        return BeliefState(
            particles=particles,
            hits=jnp.zeros((words,), jnp.uint32),
            misses=jnp.zeros((words,), jnp.uint32),
            fired=jnp.zeros((self.num_cells,), bool),
            collapses=jnp.zeros((), jnp.int32),
        )

    def _occupancy(self, particles: Int[Array, "particles ships"]) -> UInt32[Array, "particles words"]:
        masks = self._masks()
        occ = masks[0][particles[:, 0]]
        for i in range(1, len(masks)):
            occ = occ | masks[i][particles[:, i]]
        return occ

    def marginals(self, belief: BeliefState) -> Float[Array, " cells"]:
        """The estimated probability that each cell holds a ship."""
        word, bit = bit_index(self.size)
        occ = self._occupancy(belief.particles)
        cells = (occ[:, word] >> jnp.asarray(bit)[None, :]) & jnp.uint32(1)
        return jnp.mean(cells.astype(jnp.float32), axis=0)

    def act(self, belief: BeliefState, *, key: PRNGKeyArray) -> Int[Array, ""]:
        """The unfired cell of highest marginal (ties broken at random)."""
        noise = 1e-6 * jax.random.uniform(key, (self.num_cells,))
        score = jnp.where(belief.fired, -1.0, self.marginals(belief) + noise)
        return jnp.argmax(score).astype(jnp.int32)

    def _gibbs(self, particle: Int[Array, " ships"], hits, misses, u: Float[Array, "sweeps ships"]):
        masks = self._masks()
        for sweep in range(self.sweeps):
            for i, m_i in enumerate(masks):
                others = jnp.zeros_like(hits)
                for j, m_j in enumerate(masks):
                    if j != i:
                        others = others | m_j[particle[j]]
                blocked = others | misses
                needed = hits & ~others
                legal = jnp.all((m_i & blocked[None, :]) == 0, axis=-1) & jnp.all(
                    (m_i & needed[None, :]) == needed[None, :], axis=-1
                )
                # Uniform among the legal placements: the r-th legal one, r uniform in [0, count).
                count = jnp.cumsum(legal.astype(jnp.int32))
                total = count[-1]
                r = jnp.minimum(jnp.floor(u[sweep, i] * total).astype(jnp.int32), total - 1)
                new = jnp.sum(count <= r).astype(jnp.int32)
                particle = particle.at[i].set(jnp.where(total > 0, new, particle[i]))
        return particle

    def update(
        self, belief: BeliefState, cell: Int[Array, ""], hit: Bool[Array, ""], *, key: PRNGKeyArray
    ) -> BeliefState:
        """The belief after firing at `cell` and observing `hit`."""
        k_resample, k_move = jax.random.split(key)
        words = belief.hits.shape[0]
        word, bit = cell // 32, (cell % 32).astype(jnp.uint32)
        shot = jnp.where(jnp.arange(words) == word, jnp.uint32(1) << bit, jnp.uint32(0))
        hits = jnp.where(hit, belief.hits | shot, belief.hits)
        misses = jnp.where(hit, belief.misses, belief.misses | shot)

        # Filter, then replace each dropped particle by a random survivor.
        occ = self._occupancy(belief.particles)
        alive = ((occ[:, word] >> bit) & jnp.uint32(1)).astype(bool) == hit
        survivors = jnp.sum(alive)
        r = jnp.floor(jax.random.uniform(k_resample, (self.num_particles,)) * survivors).astype(jnp.int32)
        src = jnp.searchsorted(jnp.cumsum(alive), jnp.minimum(r, survivors - 1), side="right")
        src = jnp.clip(src, 0, self.num_particles - 1)
        keep = alive | (survivors == 0)
        particles = jnp.where(keep[:, None], belief.particles, belief.particles[src])

        u = jax.random.uniform(k_move, (self.num_particles, self.sweeps, len(self.ship_lengths)))
        particles = jax.vmap(lambda p, uu: self._gibbs(p, hits, misses, uu))(particles, u)
        return BeliefState(
            particles=particles,
            hits=hits,
            misses=misses,
            fired=belief.fired.at[cell].set(True),
            collapses=belief.collapses + (survivors == 0).astype(jnp.int32),
        )


class OracleEpisode(eqx.Module):
    shots: Int[Array, ""]
    episode_return: Float[Array, ""]
    collapses: Int[Array, ""]


def play_episode(oracle: ProbabilitySearch, *, key: PRNGKeyArray) -> OracleEpisode:
    """One episode of `Battleship(oracle.size, oracle.ship_lengths)` played by `oracle`.

    The oracle sees only what the partial observation gives (the hit bit of its own last shot); the board
    is drawn by the environment's own sampler. Runs until the episode terminates (at most n² shots).
    """
    env = Battleship(oracle.size, oracle.ship_lengths, "partial")
    k_env, k_belief, key = jax.random.split(key, 3)
    state, _ = env.reset(key=k_env)
    belief = oracle.init(key=k_belief)

    def body(carry):
        state, belief, key, shots, ret, done = carry
        key, k_act, k_update, k_step = jax.random.split(key, 4)
        cell = oracle.act(belief, key=k_act)
        state, ts = env.step(state, cell, key=k_step)
        hit = ts.obs["obs"][0] > 0.5
        belief = oracle.update(belief, cell, hit, key=k_update)
        return state, belief, key, shots + 1, ret + ts.reward, ts.terminated

    init = (state, belief, key, jnp.zeros((), jnp.int32), jnp.zeros((), jnp.float32), jnp.asarray(False))
    _, belief, _, shots, ret, _ = jax.lax.while_loop(
        lambda c: ~c[5] & (c[3] < env.num_cells), body, init
    )
    return OracleEpisode(shots=shots, episode_return=ret, collapses=belief.collapses)


def exact_marginals(size: int, ship_lengths: tuple[int, ...], hits: np.ndarray, misses: np.ndarray) -> np.ndarray:
    """Exact posterior occupancy by enumerating every configuration (small boards only; for tests)."""
    tables = [placement_tables(size, length)[0] for length in ship_lengths]
    total = np.zeros(size * size)
    count = 0

    def rec(i, occupied):
        nonlocal count
        if i == len(tables):
            if np.all(occupied[hits]):
                total[occupied] += 1
                count += 1
            return
        for cells in tables[i]:
            if not occupied[cells].any() and not misses[cells].any():
                occupied[cells] = True
                rec(i + 1, occupied)
                occupied[cells] = False

    rec(0, np.zeros(size * size, bool))
    return total / count
