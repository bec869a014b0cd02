"""Battleship(n) (Silver & Veness 2010), as specified in the paper's appendix.

An `n × n` board holds ships of lengths `ship_lengths` (default 5, 4, 3, 2), each horizontal or vertical,
non-overlapping. The configuration is drawn per episode **uniformly over all legal configurations** (every
ship independently uniform over its in-bounds placements, the whole configuration rejected if two ships
overlap; the first legal one of `proposals` vectorised proposals is kept, so no configuration is favoured;
55% of proposals are legal for the default). Rounds of proposals repeat until one is legal; for the default
ships, on accelerators, the 4 rounds that suffice but with probability 3e-23 are unrolled instead of a
`while_loop`, which on a GPU would synchronise with the host on every environment step (`sample_placements`,
`loop_free_rounds`); the draws are the same.

Cells are numbered row-major, `cell = row * n + col`; the action is the cell to fire at (`Discrete(n * n)`).
Reward -1 per shot, except +100 on the shot that hits the last unhit ship cell (so an episode of `s` shots
returns `101 - s`); gamma 1; terminal when every ship cell is hit. Cells already fired at are illegal: the
observation carries `action_mask` (True = may fire) and a policy must respect it. Firing at a fired cell
anyway, or at a cell off the board (an action outside `Discrete(n * n)`), costs -1 and changes nothing. The environment truncates an episode itself after `n * n` shots (a
legal policy never gets there), so the time limit follows the board size.

Observation `{"obs": ..., "action_mask": Bool[n*n]}` where `obs` is
- `partial` (n*n + 1): the hit bit of the last shot, then the one-hot of the last action (zeros at reset);
- `perfect_memory` (2 n*n): the hit plane then the miss plane (each row-major over cells);
- `full` (3 n*n): hits, misses, and the ship-occupancy plane.

A uniformly random legal policy fires until the last of the `c` ship cells in a random order of the `n*n`
cells: `E[s] = c (n*n + 1) / (c + 1)`, i.e. a mean return of `101 - 14 * 101 / 15 = 6.73` for the default.

The state keeps the ships as a precomputed occupancy grid (ship id per cell) and per-ship counters of unhit
cells, so a step is a handful of gathers, independent of the board size.
"""

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Int, PRNGKeyArray

from .._backend import loop_free_placements
from ._base import AbstractEnvironment, TimeStep, timestep
from ._spaces import Box, DictSpace, Discrete


@functools.lru_cache(maxsize=None)
def placement_tables(size: int, length: int) -> tuple[np.ndarray, np.ndarray]:
    """All in-bounds placements of a ship of `length` on a `size × size` board.

    Returns `(cells, masks)`: `cells[p]` the `length` cell indices of placement `p` (horizontal placements
    first, then vertical), `masks[p]` the same set as a bitmask in `ceil(size² / 32)` uint32 words.
    """
    n = size
    horizontal = [[r * n + c + k for k in range(length)] for r in range(n) for c in range(n - length + 1)]
    vertical = [[(r + k) * n + c for k in range(length)] for r in range(n - length + 1) for c in range(n)]
    # A ship of length 1 is the same placement both ways: count it once so that placements stay uniform.
    cells = np.asarray(horizontal if length == 1 else horizontal + vertical, np.int32)
    words = (n * n + 31) // 32
    masks = np.zeros((len(cells), words), np.uint32)
    for p, cs in enumerate(cells):
        for c in cs:
            masks[p, c // 32] |= np.uint32(1) << np.uint32(c % 32)
    return cells, masks


PLACEMENT_TABLES_MAX_BYTES = 2**30


def placement_table_bytes(size: int, ship_lengths: tuple[int, ...]) -> int:
    """The bytes of `placement_tables` for every ship: each placement's cells (int32) and bitmask (uint32 words)."""
    words = (size * size + 31) // 32
    count = [size * (size - n + 1) * (1 if n == 1 else 2) for n in ship_lengths]
    return sum(c * (n + words) * 4 for c, n in zip(count, ship_lengths))


#: The most ships a Battleship takes: every placement proposal checks each pair of ships for overlap, so the reset's
#: program grows as the square of their number (50 ships: 1,225 checks, 28 s to compile the reset alone on a CPU).
MAX_SHIPS = 32
#: Independent uniform proposals drawn at construction (fixed seed) to tell a fleet whose legal configurations are
#: too rare to sample, and how many of them must be legal: fewer than 4 in 2^17 (about 1 in 30,000) and a reset takes
#: thousands of rounds of proposals (50 ships of length 1 on 10x10, about 3 in 10^6 legal: 70 s a reset on a CPU).
#: Fleets of more than 2^10 cells draw fewer (2^27 cells in all, at least 2^12 proposals), so that the check stays
#: within seconds.
CROWDING_SAMPLES, CROWDING_MIN_LEGAL = 2**17, 4


def crowding_samples(ship_lengths: tuple[int, ...]) -> int:
    """The proposals `legal_count` draws for a fleet (`CROWDING_SAMPLES`, fewer for fleets of many cells)."""
    return min(CROWDING_SAMPLES, max(2**12, 2**27 // sum(ship_lengths)))


def _line_cover(size: int, length: int) -> np.ndarray:
    """For each index along a line of `size` cells, how many placements of a ship of `length` on it cover it."""
    i = np.arange(size)
    return (np.minimum(i, size - length) - np.maximum(0, i - length + 1) + 1).astype(np.float64)


def overlap_bound(size: int, ship_lengths: tuple[int, ...]) -> float:
    """An upper bound on the probability that a proposal (each ship uniform over its placements, independently) is
    illegal: the sum over pairs of ships of the expected number of cells both cover (a union bound)."""
    covers = []
    for length in ship_lengths:
        h = _line_cover(size, length)
        grid = np.broadcast_to(h[None, :], (size, size)) + (0.0 if length == 1 else h[:, None])
        covers.append(grid / (size * (size - length + 1) * (1 if length == 1 else 2)))
    covers = np.stack(covers)
    return float((np.sum(covers.sum(0) ** 2) - np.sum(covers**2)) / 2.0)


def _cells(size: int, length: int) -> np.ndarray:
    """The cells of every placement of a ship of `length` (as `placement_tables`'s, without the bitmasks)."""
    k = np.arange(length)
    r, c = np.meshgrid(np.arange(size), np.arange(size - length + 1), indexing="ij")
    horizontal = (r * size + c).reshape(-1, 1) + k
    vertical = (c * size + r).reshape(-1, 1) + k * size  # (start row c, column r): the transposed placements
    return horizontal if length == 1 else np.concatenate([horizontal, vertical])


@functools.lru_cache(maxsize=None)
def legal_count(size: int, ship_lengths: tuple[int, ...], samples: int, enough: int = CROWDING_MIN_LEGAL) -> int:
    """How many of `samples` independent uniform proposals (fixed NumPy seed) are legal, counted until `enough` are
    found (and `samples` where `overlap_bound` shows that at least half are). Each proposal's cells are sorted and
    checked for a repeat: the cost does not grow with the square of the ships nor with the board's bitmask words."""
    if overlap_bound(size, ship_lengths) <= 0.5:
        return samples
    tables = [_cells(size, length) for length in ship_lengths]
    rng, found, done = np.random.default_rng(0), 0, 0
    chunk = max(1, 2**22 // sum(ship_lengths))  # (at most 16 MiB of cells at a time)
    while done < samples and found < enough:
        n = min(chunk, samples - done)
        cells = np.concatenate([t[rng.integers(0, len(t), n)] for t in tables], axis=1)
        cells.sort(axis=1)
        found += int(np.sum(np.all(cells[:, 1:] != cells[:, :-1], axis=1)))
        done += n
    return found


def bit_index(size: int) -> tuple[np.ndarray, np.ndarray]:
    """For each cell, the bitmask word it lives in and its bit within that word."""
    cells = np.arange(size * size)
    return cells // 32, (cells % 32).astype(np.uint32)


def _radix_groups(counts: list[int]) -> list[list[int]]:
    """Ships grouped so that each group's joint placement index fits in 16 bits (one 32-bit random word)."""
    groups, product = [[]], 1
    for i, c in enumerate(counts):
        if groups[-1] and product * c > 2**16:
            groups.append([])
            product = 1
        groups[-1].append(i)
        product *= c
    return groups


def sample_placements(
    key: PRNGKeyArray, size: int, ship_lengths: tuple[int, ...], proposals: int = 16, rounds: int | None = None
) -> Int[Array, " ships"]:
    """A uniformly random legal configuration: one placement index per ship (into `placement_tables`).

    Random bits are the cost here, so a proposal takes one 32-bit word per group of ships whose joint index
    fits in 16 bits (two words for 5, 4, 3, 2 on 10x10), reduced modulo the group's size: the relative
    deviation from uniform is below 2^-16 (for ships of at most 2^16 placements each).

    Rounds of `proposals` proposals are drawn until one holds a legal configuration. `rounds=None`: a
    `while_loop` does that. `rounds=R`: exactly R rounds, unrolled, and the first legal proposal of the first
    round that has one is kept: the same configuration as the `while_loop` whenever that ends within R rounds.
    A while loop costs a device-to-host copy of its predicate per iteration on a GPU (a synchronisation per
    environment step, as every environment computes a reset each step); R rounds cost none. Should all R rounds
    fail, a fixed legal configuration is returned: use R only where that is vanishingly rare
    (`loop_free_rounds`).
    """
    tables = [placement_tables(size, length) for length in ship_lengths]
    counts = [len(cells) for cells, _ in tables]
    groups = _radix_groups(counts)

    key_shape, impl = jax.random.key_data(key).shape, jax.random.key_impl(key)
    key_words = math.prod(key_shape)

    def propose(key):
        # One call to the PRNG per round (its fixed cost dominates at this size): the proposals' words,
        # and the words of a fresh key for a further round.
        words = jax.random.bits(key, (proposals * len(groups) + key_words,), jnp.uint32)
        next_key = jax.random.wrap_key_data(words[-key_words:].reshape(key_shape), impl=impl)
        bits = words[: proposals * len(groups)].reshape(proposals, len(groups))
        idx = [None] * len(counts)
        for g, group in enumerate(groups):
            r = bits[:, g] % jnp.uint32(np.prod([counts[i] for i in group]))
            for i in group:  # mixed-radix digits
                idx[i] = (r % jnp.uint32(counts[i])).astype(jnp.int32)
                r = r // jnp.uint32(counts[i])
        masks = [jnp.asarray(m)[idx[i]] for i, (_, m) in enumerate(tables)]  # each (proposals, words)
        legal = jnp.ones((proposals,), bool)
        for i in range(len(masks)):
            for j in range(i + 1, len(masks)):
                legal = legal & jnp.all((masks[i] & masks[j]) == 0, axis=-1)
        # The first legal proposal: independent proposals, so it is an exact draw from the legal ones.
        first = jnp.argmax(legal)
        return next_key, jnp.stack([i[first] for i in idx]), jnp.any(legal)

    if rounds is None:
        _, idx, _ = jax.lax.while_loop(lambda c: ~c[2], lambda c: propose(c[0]), propose(key))
        return idx
    found, idx = jnp.asarray(False), jnp.asarray(fallback_configuration(size, tuple(ship_lengths)))
    for _ in range(rounds):
        key, idx_r, ok = propose(key)
        idx = jnp.where(ok & ~found, idx_r, idx)
        found = found | ok
    return idx


#: Largest probability, per reset, that `loop_free_rounds` accepts for all its rounds to fail (2^-64).
LOOP_FREE_FAILURE = 2.0**-64


@functools.lru_cache(maxsize=None)
def legal_fraction(size: int, ship_lengths: tuple[int, ...], samples: int = 200_000) -> float:
    """Fraction of independent uniform proposals (one placement per ship) that do not overlap, estimated
    from `samples` proposals with a fixed NumPy seed (0.556 for 5, 4, 3, 2 on 10x10)."""
    rng = np.random.default_rng(0)
    masks = []
    for length in ship_lengths:
        cells, m = placement_tables(size, length)
        masks.append(np.asarray(m)[rng.integers(0, len(cells), samples)])
    legal = np.ones(samples, bool)
    for i in range(len(masks)):
        for j in range(i + 1, len(masks)):
            legal &= np.all((masks[i] & masks[j]) == 0, axis=-1)
    return float(legal.mean())


@functools.lru_cache(maxsize=None)
def loop_free_rounds(size: int, ship_lengths: tuple[int, ...], proposals: int, max_rounds: int = 8) -> int | None:
    """The fewest rounds of `proposals` proposals that all fail with probability below `LOOP_FREE_FAILURE`
    (from `legal_fraction`, with its estimate lowered by a 5σ margin), or None (use the `while_loop`) if that
    takes more than `max_rounds`. 4 for the default ships on 10x10 with 16 proposals (failure ≈ 3e-23)."""
    n = 200_000
    p = legal_fraction(size, ship_lengths, n)
    p = p - 5.0 * math.sqrt(max(p * (1.0 - p), 1e-12) / n)
    if p <= 0.0:
        return None
    per_round = proposals * math.log1p(-p) if p < 1.0 else -math.inf
    rounds = max(1, math.ceil(math.log(LOOP_FREE_FAILURE) / per_round))
    return rounds if rounds <= max_rounds else None


@functools.lru_cache(maxsize=None)
def fallback_configuration(size: int, ship_lengths: tuple[int, ...]) -> np.ndarray:
    """A fixed legal configuration (the first in lexicographic order of placement indices), returned by the
    loop-free sampler in the case that all its rounds fail."""
    tables = [placement_tables(size, length) for length in ship_lengths]

    def search(i, used, chosen):
        if i == len(tables):
            return chosen
        for j, m in enumerate(np.asarray(tables[i][1])):
            if not np.any(m & used):
                found = search(i + 1, used | m, chosen + [j])
                if found is not None:
                    return found
        return None

    found = search(0, np.zeros_like(np.asarray(tables[0][1])[0]), [])
    if found is None:
        raise ValueError(f"no legal configuration of ships {ship_lengths} on a {size}x{size} board")
    return np.asarray(found, np.int32)


def ships_grid(
    placements: Int[Array, " ships"], size: int, ship_lengths: tuple[int, ...]
) -> Int[Array, " cells"]:
    """The occupancy grid of a configuration: the ship id in each cell, -1 for water."""
    tables = [jnp.asarray(placement_tables(size, length)[0]) for length in ship_lengths]
    cells = jnp.concatenate([table[placements[i]] for i, table in enumerate(tables)])
    ids = jnp.asarray(np.repeat(np.arange(len(ship_lengths)), ship_lengths), jnp.int32)
    return jnp.full((size * size,), -1, jnp.int32).at[cells].set(ids)


class BattleshipState(eqx.Module):
    ships: Int[Array, " cells"]  # ship id in each cell (row-major), -1 for water
    fired: Bool[Array, " cells"]
    cells_left: Int[Array, " ships"]  # unhit cells of each ship
    last_action: Int[Array, ""]  # -1 before the first shot
    last_hit: Bool[Array, ""]
    steps: Int[Array, ""]  # shots so far, for the built-in n*n time limit


class Battleship(AbstractEnvironment[BattleshipState]):
    """Battleship on a `size × size` board with ships of `ship_lengths`."""

    size: int = eqx.field(static=True, default=10)
    ship_lengths: tuple[int, ...] = eqx.field(static=True, default=(5, 4, 3, 2))
    observability: str = eqx.field(static=True, default="partial")
    proposals: int = eqx.field(static=True, default=16)  # vectorised placement proposals per rejection round
    # Resets draw placements in `loop_free_rounds` rounds of proposals (True) or in a `while_loop` until one is legal
    # (False): the same draws either way (`sample_placements`). None: the platform's choice
    # (`pobax._backend.loop_free_placements`), set by `pobax.env.for_backend`; the CPU's where none was set.
    loop_free: bool | None = eqx.field(static=True, default=None)

    observabilities = ("partial", "perfect_memory", "full")

    def __check_init__(self):
        if self.observability not in self.observabilities:
            raise ValueError(
                f"Battleship has observabilities {self.observabilities}, got {self.observability!r}."
            )
        if not self.ship_lengths or any(not 1 <= length <= self.size for length in self.ship_lengths):
            raise ValueError(
                f"Battleship needs at least one ship, each of length 1..size={self.size}; got ship_lengths="
                f"{self.ship_lengths}. Use a larger board or shorter ships."
            )
        if isinstance(self.proposals, bool) or not isinstance(self.proposals, (int, np.integer)) \
                or not 1 <= self.proposals <= 4096:
            raise ValueError(f"Battleship's proposals (placements drawn at once per rejection round) must be an "
                             f"integer in [1, 4096], got {self.proposals!r}.")
        if (need := placement_table_bytes(self.size, self.ship_lengths)) > PLACEMENT_TABLES_MAX_BYTES:
            raise ValueError(  # the placement bitmasks grow as size**4 (a 100x100 board: 94 MiB)
                f"Battleship's placement tables for a {self.size}x{self.size} board take {need / 2**30:,.1f} GiB, more "
                f"than {PLACEMENT_TABLES_MAX_BYTES // 2**30} GiB; use a smaller board.")
        if sum(self.ship_lengths) > self.size * self.size // 2:
            # Rejection sampling needs a reasonable share of legal configurations.
            raise ValueError(
                f"Ships of lengths {self.ship_lengths} ({sum(self.ship_lengths)} cells) crowd a "
                f"{self.size}x{self.size} board; keep them to at most half of its {self.size**2} cells."
            )
        if len(self.ship_lengths) > MAX_SHIPS:
            raise ValueError(f"Battleship takes at most {MAX_SHIPS} ships (each pair is checked for overlap in every "
                             f"placement proposal: the reset's program grows as their square), got "
                             f"{len(self.ship_lengths)}; use fewer, longer ships.")
        lengths = tuple(int(n) for n in self.ship_lengths)
        samples = crowding_samples(lengths)
        if (legal := legal_count(self.size, lengths, samples)) < CROWDING_MIN_LEGAL:
            raise ValueError(  # a reset draws rounds of proposals until one is legal: it would take thousands
                f"Ships of lengths {lengths} crowd a {self.size}x{self.size} board: {legal} of {samples:,} "
                f"random placements of them are legal (at least {CROWDING_MIN_LEGAL} needed), so every reset would "
                f"search for seconds to hours; use fewer or shorter ships or a larger board.")

    @property
    def num_cells(self) -> int:
        return self.size * self.size

    @property
    def gamma(self) -> float:
        return 1.0

    @property
    def max_steps_in_episode(self) -> int:
        return self.num_cells  # a legal policy always finishes within n*n shots

    @property
    def action_space(self) -> Discrete:
        return Discrete(self.num_cells)

    @property
    def obs_size(self) -> int:
        planes = {"partial": None, "perfect_memory": 2, "full": 3}[self.observability]
        return self.num_cells + 1 if planes is None else planes * self.num_cells

    @property
    def observation_space(self) -> DictSpace:
        mask = Box(0.0, 1.0, (self.num_cells,), jnp.bool_)
        return DictSpace({"obs": Box(0.0, 1.0, (self.obs_size,)), "action_mask": mask})

    def random_policy_return(self) -> float:
        """Mean return of a uniformly random legal policy (the last ship cell's rank in a random order)."""
        c, m = sum(self.ship_lengths), self.num_cells
        return 101.0 - c * (m + 1) / (c + 1)

    def observe(self, state: BattleshipState) -> dict[str, Array]:
        """The observation of `state` under this environment's observability, with the action mask."""
        occupied = state.ships >= 0
        hits = (state.fired & occupied).astype(jnp.float32)
        misses = (state.fired & ~occupied).astype(jnp.float32)
        if self.observability == "partial":
            last = jax.nn.one_hot(state.last_action, self.num_cells, dtype=jnp.float32)  # zeros for -1
            obs = jnp.concatenate([state.last_hit[None].astype(jnp.float32), last])
        elif self.observability == "perfect_memory":
            obs = jnp.concatenate([hits, misses])
        else:
            obs = jnp.concatenate([hits, misses, occupied.astype(jnp.float32)])
        return {"obs": obs, "action_mask": ~state.fired}

    def state_from_placements(self, placements: Int[Array, " ships"]) -> BattleshipState:
        """The start state of the configuration `placements` (one index per ship into `placement_tables`)."""
        return BattleshipState(
            ships=ships_grid(placements, self.size, self.ship_lengths),
            fired=jnp.zeros((self.num_cells,), bool),
            cells_left=jnp.asarray(self.ship_lengths, jnp.int32),
            last_action=jnp.asarray(-1, jnp.int32),
            last_hit=jnp.asarray(False),
            steps=jnp.asarray(0, jnp.int32),
        )

    def reset(self, *, key: PRNGKeyArray) -> tuple[BattleshipState, TimeStep]:
        lengths = tuple(self.ship_lengths)
        loop_free = loop_free_placements("cpu") if self.loop_free is None else self.loop_free
        rounds = loop_free_rounds(self.size, lengths, self.proposals) if loop_free else None
        placements = sample_placements(key, self.size, lengths, self.proposals, rounds)
        state = self.state_from_placements(placements)
        return state, timestep(self.observe(state))

    def step(
        self, state: BattleshipState, action: Int[Array, ""], *, key: PRNGKeyArray
    ) -> tuple[BattleshipState, TimeStep]:
        del key  # deterministic
        cell = self.action_space.as_action(action)
        valid = (cell >= 0) & (cell < self.num_cells)  # a cell off the board: a wasted shot, as a fired cell is
        ship = jnp.where(valid, state.ships[jnp.clip(cell, 0, self.num_cells - 1)], -1)
        on_ship = ship >= 0
        new_hit = on_ship & ~state.fired[jnp.clip(cell, 0, self.num_cells - 1)]
        # Water (-1) points at ship 0 with a zero decrement: no out-of-range index, no branch.
        cells_left = state.cells_left.at[jnp.maximum(ship, 0)].add(-new_hit.astype(jnp.int32))
        won = new_hit & (jnp.sum(cells_left) == 0)
        new_state = BattleshipState(
            ships=state.ships,
            fired=state.fired.at[jnp.clip(cell, 0, self.num_cells - 1)].max(valid),
            cells_left=cells_left,
            last_action=cell,
            last_hit=on_ship,
            steps=state.steps + 1,
        )
        # A legal policy is done within n*n shots; one that repeats cells is cut there (bootstrapped).
        truncated = ~won & (new_state.steps >= self.num_cells)
        reward = jnp.where(won, 100.0, -1.0)
        return new_state, timestep(self.observe(new_state), reward, terminated=won, truncated=truncated)
