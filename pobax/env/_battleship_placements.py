"""Battleship's ship configurations: every placement of a ship (`placement_tables`), a uniform draw of a legal
configuration by rounds of vectorised proposals (`sample_placements`), how many rounds make the draw loop-free
(`loop_free_rounds`), and which fleets a board can hold at all (`check_fleet`). The environment is `_battleship`."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int, PRNGKeyArray


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
#: A fleet is refused where fewer than `CROWDING_MIN_LEGAL` of `CROWDING_SAMPLES` proposals (about 1 in 30,000) are
#: legal: a reset would take thousands of rounds of proposals (50 ships of length 1 on 10x10, about 3 in 10^6 legal:
#: 70 s a reset on a CPU). Fleets of more than 2^10 cells draw fewer (2^27 cells in all, at least 2^12 proposals).
CROWDING_SAMPLES, CROWDING_MIN_LEGAL = 2**17, 4


@functools.lru_cache(maxsize=None)
def legal_count(size: int, ship_lengths: tuple[int, ...], samples: int, enough: int | None = None) -> int:
    """How many of `samples` independent uniform proposals (one placement per ship, fixed NumPy seed) do not overlap,
    counted until `enough` are found (in batches of at most 2^22 cells; all at once without `enough`). Each
    proposal's cells are sorted and checked for a repeat: the cost grows neither with the square of the ships nor
    with the board's bitmask words."""
    tables = [placement_tables(size, length)[0] for length in ship_lengths]
    rng, found, done = np.random.default_rng(0), 0, 0
    batch = samples if enough is None else max(1, 2**22 // sum(ship_lengths))
    while done < samples and (enough is None or found < enough):
        n = min(batch, samples - done)
        cells = np.concatenate([t[rng.integers(0, len(t), n)] for t in tables], axis=1)
        cells.sort(axis=1)
        found += int(np.sum(np.all(cells[:, 1:] != cells[:, :-1], axis=1)))
        done += n
    return found


def check_fleet(size: int, ship_lengths: tuple[int, ...]) -> None:
    """A one-line ValueError unless a reset can draw `ship_lengths` on a `size × size` board in a few rounds of
    proposals: at most `MAX_SHIPS` ships, legal placements not too rare to sample (`legal_count`)."""
    if len(ship_lengths) > MAX_SHIPS:
        raise ValueError(f"Battleship takes at most {MAX_SHIPS} ships (each pair is checked for overlap in every "
                         f"placement proposal: the reset's program grows as their square), got "
                         f"{len(ship_lengths)}; use fewer, longer ships.")
    samples = min(CROWDING_SAMPLES, max(2**12, 2**27 // sum(ship_lengths)))
    if (legal := legal_count(size, ship_lengths, samples, CROWDING_MIN_LEGAL)) < CROWDING_MIN_LEGAL:
        raise ValueError(  # a reset draws rounds of proposals until one is legal: it would take thousands
            f"Ships of lengths {ship_lengths} crowd a {size}x{size} board: {legal} of {samples:,} random "
            f"placements of them are legal (at least {CROWDING_MIN_LEGAL} needed), so every reset would search "
            f"for seconds to hours; use fewer or shorter ships or a larger board.")


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


def legal_fraction(size: int, ship_lengths: tuple[int, ...], samples: int = 200_000) -> float:
    """Fraction of independent uniform proposals (one placement per ship) that do not overlap, estimated from
    `samples` proposals with a fixed NumPy seed (`legal_count`; 0.555 for 5, 4, 3, 2 on 10x10)."""
    return legal_count(size, ship_lengths, samples) / samples


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
