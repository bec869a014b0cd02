"""`check_memory`: a test that any memory cell, built in or your own, satisfies the memory contract (stated once,
in `pobax.memory.AbstractMemory`'s module, pobax/memory/_base.py).

`check_memory(cell)` checks each point of the contract on random inputs, under `jax.jit` and `jax.vmap`, plus finite gradients,
and raises `AssertionError` naming the broken property. Run it in your tests:

    from pobax.memory.testing import check_memory
    check_memory(MyCell(5, 16, key=jax.random.key(0)))
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._base import AbstractMemory

__all__ = ["check_memory"]


@dataclasses.dataclass
class _Checker:
    cell: object
    atol: float
    rtol: float

    def fail(self, message: str):
        raise AssertionError(f"check_memory({type(self.cell).__name__}): {message}")

    def close(self, what: str, got, want) -> None:
        """Every leaf of `got` equals `want` up to the tolerances; otherwise fail naming `what`."""
        g_leaves, w_leaves = jax.tree.leaves(got), jax.tree.leaves(want)
        if jax.tree.structure(got) != jax.tree.structure(want):
            self.fail(f"{what}: the carries differ in structure ({jax.tree.structure(got)} vs "
                      f"{jax.tree.structure(want)}).")
        for g, w in zip(g_leaves, w_leaves):
            g, w = np.asarray(g), np.asarray(w)
            if g.shape != w.shape:
                self.fail(f"{what}: shapes differ ({g.shape} vs {w.shape}).")
            if g.dtype == bool or np.issubdtype(g.dtype, np.integer):
                if not np.array_equal(g, w):
                    self.fail(f"{what} ({int(np.sum(g != w))} of {g.size} {g.dtype} entries differ).")
            elif not np.allclose(g, w, atol=self.atol, rtol=self.rtol):
                diff = float(np.max(np.abs(g.astype(np.complex128) - w)))
                self.fail(f"{what} (largest difference {diff:.3g}; atol={self.atol:g}, rtol={self.rtol:g}).")

    def same_layout(self, what: str, carry, reference) -> None:
        """`carry` has `reference`'s structure, shapes and dtypes."""
        def layout(tree):
            return jax.tree.structure(tree), [(np.shape(x), jnp.result_type(x)) for x in jax.tree.leaves(tree)]

        if layout(carry) != layout(reference):
            self.fail(f"the carry {what} is not laid out like init_carry() (structure, shapes and dtypes must stay "
                      f"the same from call to call): {layout(carry)} vs {layout(reference)}.")


def _starts(batch: int, time: int) -> np.ndarray:
    """Episode starts for `batch` environments: a start at 0 and another inside; none (the episode goes on from
    the incoming carry); starts on consecutive steps and at the last step; then varied patterns."""
    starts = np.zeros((batch, time), bool)
    patterns = [[0, time // 3], [], [1, 2, time - 1], [time // 2]]
    for b in range(batch):
        for t in patterns[b % len(patterns)]:
            starts[b, min(t, time - 1)] = True
    return starts


def check_memory(cell, *, time: int = 12, batch: int = 3, seed: int = 0, atol: float = 1e-5, rtol: float = 1e-4,
                 grad: bool = True) -> None:
    """Check that `cell` satisfies the memory contract (this module's docstring); raise `AssertionError` otherwise.

    On `batch` environments of `time` random inputs (with episode starts at the first step, inside, on consecutive
    steps, at the last step, and none), starting from a carry left by an earlier sequence, it checks:

    1. the cell is an `AbstractMemory` whose leaves are all arrays (everything else `eqx.field(static=True)`),
       with integer `in_size` and `out_size`;
    2. outputs have shape (time, out_size), are finite floats, and the carry keeps `init_carry()`'s structure,
       shapes and dtypes;
    3. one call under `jax.jit(jax.vmap(...))` over environments equals the jitted call of each environment
       alone, and `jax.vmap` over two copies of the cell's parameters (as over seeds) equals the unbatched cell;
    4. stepping one input at a time, and splitting the sequence into two calls, give the outputs and final carry
       of one call over the whole sequence (resets included);
    5. no information crosses an episode start: from each environment's every start on, outputs equal
       those of a fresh cell (`init_carry()` with no start flag, so a reset must give exactly that state) given
       only the inputs from that start, and so do the outputs of further inputs after the call (a carry may keep
       stale values, e.g. masked ones, that never reach an output); and no gradient flows from them into earlier
       inputs or into the incoming carry;
    6. with `grad`, gradients of the outputs and final carry with respect to the parameters and the inputs are
       finite, and not all zero.

    `atol`/`rtol` bound the float rounding allowed between the ways of computing the same thing (e.g. an
    associative scan against a step-by-step loop). `seed` draws the inputs.
    """
    chk = _Checker(cell, atol, rtol)
    if not isinstance(cell, AbstractMemory):
        chk.fail(f"a memory cell must subclass pobax.memory.AbstractMemory, got {type(cell).__mro__[1:]}.")
    for attr in ("in_size", "out_size"):
        v = getattr(cell, attr, None)
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            chk.fail(f"{attr} must be a positive int field, got {v!r}.")
    for path, leaf in jax.tree_util.tree_flatten_with_path(cell)[0]:
        if not eqx.is_array(leaf):
            chk.fail(f"field {jax.tree_util.keystr(path)} is a {type(leaf).__name__}, not an array: mark every field "
                     f"that is not a JAX array eqx.field(static=True) (pobax creates the network under jax.vmap).")
    if time < 4 or batch < 1:
        raise ValueError("check_memory needs time >= 4 and batch >= 1")

    # Inputs and results live on the host (numpy): only the cell's own calls are compiled.
    rng = np.random.default_rng(seed)
    n_in, n_out = cell.in_size, cell.out_size
    normal = lambda *shape: rng.standard_normal(shape, dtype=np.float32)  # noqa: E731
    starts = _starts(batch, time)
    xs = normal(batch, time, n_in)
    init = jax.device_get(cell.init_carry())
    fresh = jax.tree.map(lambda c: np.repeat(np.asarray(c)[None], batch, axis=0), init)
    nth = lambda tree, i: jax.tree.map(lambda c: c[i], tree)  # noqa: E731
    seq = jax.jit(jax.vmap(lambda c, x, s: cell(c, x, s)))

    def run(fn, *args):
        return jax.device_get(fn(*args))

    # A carry from an earlier episode: the sequences below continue it where they have no start at step 0.
    warm_starts = np.zeros((batch, time), bool)
    warm_starts[:, 0] = True
    warm, _ = run(seq, fresh, normal(batch, time, n_in), warm_starts)
    chk.same_layout("after a call", nth(warm, 0), init)

    # 2. shapes, dtypes, finiteness
    carry_seq, ys = run(seq, warm, xs, starts)
    if ys.shape != (batch, time, n_out):
        chk.fail(f"outputs must have shape (time, out_size) = {(time, n_out)} per environment, got "
                 f"{tuple(ys.shape[1:])}.")
    if not np.issubdtype(ys.dtype, np.floating):
        chk.fail(f"outputs must be real floats, got {ys.dtype}.")
    if not np.all(np.isfinite(ys)):
        chk.fail("outputs are not finite (NaN or inf) on standard-normal inputs.")
    chk.same_layout("after a call with resets", nth(carry_seq, 0), init)

    # 3. jit + vmap over environments vs one environment at a time; vmap over parameters (seeds)
    one = jax.jit(lambda c, x, s: cell(c, x, s))
    for b in range(batch):
        c_b, y_b = run(one, nth(warm, b), xs[b], starts[b])
        chk.close(f"jax.vmap(cell) over environments differs from cell on environment {b} alone (outputs)", ys[b], y_b)
        chk.close(f"jax.vmap(cell) over environments differs from cell on environment {b} alone (final carry)",
                  nth(carry_seq, b), c_b)
    params, static = eqx.partition(cell, eqx.is_array)
    two = jax.tree.map(lambda p: np.stack([np.asarray(p)] * 2), params)
    per_seed = jax.jit(jax.vmap(lambda p, c, x, s: eqx.combine(p, static)(c, x, s), in_axes=(0, None, None, None)))
    carry_two, ys_two = run(per_seed, two, nth(warm, 0), xs[0], starts[0])
    for i in range(2):
        chk.close("jax.vmap over the cell's parameters (one cell per seed) differs from the unbatched cell",
                  (nth(carry_two, i), ys_two[i]), (nth(carry_seq, 0), ys[0]))

    # 4. one step at a time, and two calls, equal one call over the sequence
    step = jax.jit(jax.vmap(lambda c, x, s: cell(c, x[None], s[None])))

    def stepped(carry, inputs, flags):
        outs, carries = [], []
        for t in range(inputs.shape[1]):
            carry, y = run(step, carry, inputs[:, t], flags[:, t])
            if y.shape != (batch, 1, n_out):
                chk.fail(f"a one-step call must return outputs of shape (1, out_size), got {tuple(y.shape[1:])}.")
            chk.same_layout("after a one-step call", nth(carry, 0), init)
            outs.append(y[:, 0])
            carries.append(carry)
        return carries, np.stack(outs, axis=1)

    carries, ys_step = stepped(warm, xs, starts)
    for b in range(batch):
        t_bad = next((t for t in range(time) if not np.allclose(ys_step[b, t], ys[b, t], atol=atol, rtol=rtol)), None)
        if t_bad is not None:
            chk.fail(f"one step at a time differs from one call over the sequence at step {t_bad} of environment {b} "
                     f"(starts at {np.flatnonzero(starts[b]).tolist()}; largest difference "
                     f"{float(np.max(np.abs(ys_step[b] - ys[b]))):.3g}): the output must not depend on how a "
                     f"sequence is cut into calls.")
    chk.close("one step at a time ends with another carry than one call over the sequence", carries[-1], carry_seq)
    cut = time // 2 + 1
    c1, y1 = run(seq, warm, xs[:, :cut], starts[:, :cut])
    c2, y2 = run(seq, c1, xs[:, cut:], starts[:, cut:])
    chk.close(f"two calls (steps 0-{cut - 1}, then {cut}-{time - 1}) differ from one call over the sequence",
              (c2, np.concatenate([y1, y2], axis=1)), (carry_seq, ys))

    # 5. nothing crosses an episode start: from each environment's every start (on consecutive steps too), a fresh
    # cell (stepped, as checked above, from init_carry() with no start flag: a reset must give exactly that state) on
    # the inputs from that start gives the same outputs, and from its last start its carry the same later outputs
    later, no_starts = normal(batch, 4, n_in), np.zeros((batch, 4), bool)
    most = int(starts.sum(axis=1).max())
    for k in [*range(most - 1), -1] if most else []:
        first = k != -1  # (the last start's pass also checks the carry)
        t0s = [int(np.flatnonzero(row)[k]) if (row.any() if k == -1 else row.sum() > k) else None for row in starts]
        idx = np.array([[min((t0 or 0) + r, time - 1) for r in range(time)] for t0 in t0s])
        rows = np.arange(batch)[:, None]
        aligned_starts = starts[rows, idx]
        aligned_starts[:, 0] = False
        carries_f, ys_fresh = stepped(fresh, xs[rows, idx], aligned_starts)
        for b, t0 in enumerate(t0s):
            if t0 is None:
                continue
            end = next((int(t) for t in np.flatnonzero(starts[b]) if t > t0), time)
            got, want = ys[b, t0:end], ys_fresh[b, : end - t0]
            if not np.allclose(got, want, atol=atol, rtol=rtol):
                chk.fail(f"information crosses an episode start: on environment {b}, the outputs from the start at "
                         f"step {t0} differ from a fresh cell's (init_carry()) on the same inputs (largest "
                         f"difference {float(np.max(np.abs(got - want))):.3g}): reset the carry to init_carry() "
                         f"before every input whose starts[t] is true.")
        if not first:  # the carry may keep stale values (masked, say), but they must not reach later outputs
            fresh_end = jax.tree.map(lambda *cs: np.stack([c[b] for b, c in enumerate(cs)]),
                                     *[carries_f[time - 1 - (t0 or 0)] for t0 in t0s])
            _, y_on = run(seq, carry_seq, later, no_starts)
            _, y_on_fresh = run(seq, fresh_end, later, no_starts)
            for b, t0 in enumerate(t0s):
                if t0 is not None and not np.allclose(y_on[b], y_on_fresh[b], atol=atol, rtol=rtol):
                    chk.fail(f"information crosses an episode start: on environment {b}, the carry after the episode "
                             f"that starts at step {t0} leads to other outputs (on the same later inputs) than a "
                             f"fresh cell's carry after the same inputs (largest difference "
                             f"{float(np.max(np.abs(y_on[b] - y_on_fresh[b]))):.3g}).")
    if not grad:
        return
    w_y = normal(time, n_out)

    # no gradient from outputs at or after a start into earlier inputs or the incoming carry
    b = int(np.flatnonzero(starts.any(axis=1))[0])
    t0 = int(np.flatnonzero(starts[b])[-1])

    def after_start(x, c):
        c_out, y = cell(c, x, jnp.asarray(starts[b]))
        return jnp.sum(y[t0:] * w_y[t0:]) + _carry_sum(c_out)

    g_x, g_c = run(jax.jit(jax.grad(after_start, argnums=(0, 1), allow_int=True)), xs[b], nth(warm, b))
    leaked = float(np.max(np.abs(g_x[:t0]))) if t0 else 0.0
    leaked_c = max([float(np.max(np.abs(g))) for g in _float_leaves(g_c)] or [0.0])
    if max(leaked, leaked_c) > atol:
        chk.fail(f"information crosses an episode start: outputs from the start at step {t0} have gradient "
                 f"{max(leaked, leaked_c):.3g} with respect to "
                 f"{'inputs before it' if leaked > atol else 'the incoming carry'}.")

    # 6. finite, non-trivial gradients through resets
    diff, nondiff = eqx.partition(params, eqx.is_inexact_array)  # integer arrays (e.g. index tables) stay fixed

    def loss(p, x):
        c_out, y = jax.vmap(eqx.combine(p, nondiff, static))(warm, x, jnp.asarray(starts))
        return jnp.sum(y * w_y[None]) + _carry_sum(c_out)

    g_p, g_xs = run(jax.jit(jax.grad(loss, argnums=(0, 1))), diff, xs)
    leaves = _float_leaves(g_p)
    if not all(np.all(np.isfinite(g)) for g in leaves) or not np.all(np.isfinite(g_xs)):
        chk.fail("gradients are not finite (NaN or inf) on standard-normal inputs.")
    if leaves and not any(np.any(g != 0) for g in leaves):
        chk.fail("every gradient with respect to the parameters is zero: the outputs do not depend on them.")


def _float_leaves(tree) -> list:
    return [x for x in jax.tree.leaves(tree) if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.inexact)]


def _carry_sum(carry):
    """A scalar that depends on every float leaf of a carry (its real part for complex leaves)."""
    return sum((jnp.sum(jnp.real(x)) for x in _float_leaves(carry)), jnp.zeros(()))
