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

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Int, PRNGKeyArray

from .._backend import loop_free_placements
from ._base import AbstractEnvironment, TimeStep, timestep
from ._battleship_placements import (PLACEMENT_TABLES_MAX_BYTES, check_fleet, loop_free_rounds, placement_table_bytes,
                                     placement_tables, sample_placements)
from ._spaces import Box, DictSpace, Discrete


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
        check_fleet(self.size, tuple(int(n) for n in self.ship_lengths))

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
