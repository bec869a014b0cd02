"""The memory zoo and the plug-in path: every zoo cell satisfies the memory contract (`check_memory`, under jit and
vmap, with the jaxtyping checks of the pytest configuration on), `check_memory` catches broken cells, and a user's
cell given as `package.module:ClassName` trains from the command line, resumes, and joins the gap and the benchmark.
"""

import json
import re
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import pytest

import cli
from pobax.agent import (ConfigError, Runs, TrainConfig, apply_preset, config_from_dict, load_preset, paper_preset,
                         validate)
from pobax.env import spec
from pobax.eval import benchmark_plan
from pobax.memory import FFM, GRU, LRU, LSTM, MEMORIES, S6, ZOO, AbstractMemory, Dense, memory_class
from pobax.memory.testing import check_memory

IN, H = 5, 8


@pytest.mark.parametrize("name", [n if n == "lstm" else pytest.param(n, marks=pytest.mark.slow) for n in ZOO])
def test_zoo_cell_satisfies_the_contract(name):
    cls = memory_class(name)
    assert cls is {"lstm": LSTM, "lru": LRU, "s6": S6, "ffm": FFM}[name]
    cell = cls(IN, H, key=jax.random.key(0))
    assert (cell.in_size, cell.out_size) == (IN, H)
    assert "arXiv" in cls.__doc__ or "Neural Computation" in cls.__doc__  # its paper is cited
    check_memory(cell)


def test_zoo_cells_are_built_in_and_associative_ones_replay_with_an_associative_scan():
    assert set(ZOO) <= set(MEMORIES) and MEMORIES[:3] == ("memoryless", "gru", "trxl")
    xs, starts = jnp.ones((16, IN)), jnp.zeros(16, bool).at[5].set(True)
    for cls in (LRU, S6, FFM):
        cell = cls(IN, H, key=jax.random.key(1))
        jaxpr = str(jax.make_jaxpr(lambda c, x, s: cell(c, x, s))(cell.init_carry(), xs, starts))
        assert "scan" not in jaxpr  # no sequential loop: associative_scan traces to log-depth slices and adds
    lstm = LSTM(IN, H, key=jax.random.key(1))
    assert "scan" in str(jax.make_jaxpr(lambda c, x, s: lstm(c, x, s))(lstm.init_carry(), xs, starts))


@pytest.mark.slow
def test_own_lru_computes_memaxs_lru_in_real_arithmetic():
    """pobax's LRU (real and imaginary parts as real arrays) is memax's complex LRU: with the same weights, the same
    outputs over a sequence with an episode start inside it (so the zoo's LRU records from memax's stay valid)."""
    from memax.equinox.semigroups.lru import LRU as MemaxLRU

    xs = jax.random.normal(jax.random.key(2), (24, IN))
    starts = jnp.zeros(24, bool).at[0].set(True).at[11].set(True)
    lru = LRU(IN, H, key=jax.random.key(0))
    memax_lru = eqx.tree_at(
        lambda f: (f.nu_log, f.theta_log, f.gamma_log, f.B_re, f.B_im, f.C_re, f.C_im, f.D),
        MemaxLRU(H, H, jax.random.key(1)),
        (lru.nu_log, lru.theta_log, lru.gamma_log, lru.b_re, lru.b_im, lru.c_re, lru.c_im, lru.d))
    _, ys = lru(lru.init_carry(), xs, starts)
    _, expected = memax_lru(memax_lru.initialize_carry(), (jax.nn.relu(lru.pre(xs)), starts))
    assert jnp.allclose(ys, expected, atol=1e-5)
    assert not jnp.allclose(ys[11:], lru(lru.init_carry(), xs, jnp.zeros(24, bool).at[0].set(True))[1][11:])


@pytest.mark.slow
def test_own_ffm_is_memaxs_ffm_from_the_same_key():
    """pobax's FFM builds memax's weights from the same key and computes memax's function: the same outputs, carried
    state and parameter gradients over a sequence with an episode start inside it, from a carry that is not zero (so
    the zoo's FFM records, measured with memax's cell, stay valid)."""
    from memax.equinox.semigroups.ffm import FFM as MemaxFFM

    key = jax.random.key(3)
    ffm = FFM(IN, H, key=key)
    theirs = MemaxFFM(H, ffm.trace_size, ffm.context_size, jax.random.split(key)[1])
    m = ffm.trace_size
    assert jnp.array_equal(ffm.w_in, jnp.concatenate([theirs.pre.weight, theirs.gate_in.linear.weight,
                                                       theirs.gate_out.linear.weight]))
    assert jnp.array_equal(ffm.w_mix, theirs.mix.weight) and jnp.array_equal(ffm.b_mix, theirs.mix.bias)
    xs = jax.random.normal(jax.random.key(2), (24, IN))
    starts = jnp.zeros(24, bool).at[15].set(True)
    carry, _ = ffm(ffm.init_carry(), xs[::-1], jnp.zeros(24, bool))  # some state to start from
    u = jax.nn.relu(ffm.pre(xs))

    def ours(model):
        (s_re, s_im), ys = model(carry, xs, starts)
        return jnp.sum(ys**2) + jnp.sum(s_re * s_im), (ys, s_re, s_im)

    def memax(model):
        states, ys = model(((jax.lax.complex(*carry), jnp.array(24, jnp.int32)), jnp.array(False)), (u, starts))
        s = model.latest_recurrent_state(states)[0][0]
        return jnp.sum(ys**2) + jnp.sum(s.real * s.imag), (ys, s.real, s.imag)

    (_, out), grads = eqx.filter_value_and_grad(ours, has_aux=True)(ffm)
    (_, expected), g = eqx.filter_value_and_grad(memax, has_aux=True)(theirs)
    for a, b in zip(out, expected):
        assert jnp.allclose(a, b, atol=1e-5)
    for a, b in ((grads.alpha, g.algebra.algebra.params[0]), (grads.omega, g.algebra.algebra.params[1]),
                 (grads.w_mix, g.mix.weight), (grads.w_in[:m], g.pre.weight),
                 (grads.w_in[m:2 * m], g.gate_in.linear.weight), (grads.w_in[2 * m:], g.gate_out.linear.weight)):
        assert jnp.allclose(a, b, atol=1e-4 * float(jnp.abs(b).max())), (a, b)
    # the episode start at step 15 forgets the carry: from there on, a zero carry gives the same outputs
    _, from_zero = ffm(ffm.init_carry(), xs, starts)
    assert jnp.allclose(out[0][15:], from_zero[15:], atol=1e-6)
    assert not jnp.allclose(out[0][:15], from_zero[:15], atol=1e-3)


@pytest.mark.slow
def test_linear_recurrence_gradient_is_autodiffs():
    """The LRU's scan has a hand-written backward (the adjoint recurrence): the same gradients as
    differentiating through `jax.lax.associative_scan`, episode starts (zero decays) and the carry included."""
    from pobax.memory._lru import _scan, complex_affine_scan

    k = jax.random.split(jax.random.key(0), 7)
    time, n = 29, 5
    keep = jnp.where(jax.random.bernoulli(k[0], 0.15, (time, 1)), 0.0, 1.0)
    a = (keep * 0.9 * jax.random.uniform(k[1], (time, n)), keep * 0.4 * jax.random.normal(k[2], (time, n)))
    b = (jax.random.normal(k[3], (time, n)), jax.random.normal(k[4], (time, n)))
    x0 = (jax.random.normal(k[5], (n,)), jax.random.normal(k[6], (n,)))

    def loss(scan, a, b, x0):
        x_re, x_im = scan(a, b, x0)
        return jnp.sum(jnp.sin(x_re) * x_im) + jnp.sum(x_re**2)

    def by_autodiff(a, b, x0):
        (a_re, a_im), (b_re, b_im), (x0_re, x0_im) = a, b, x0
        b_re = b_re.at[0].add(a_re[0] * x0_re - a_im[0] * x0_im)
        b_im = b_im.at[0].add(a_re[0] * x0_im + a_im[0] * x0_re)
        return _scan(a_re, a_im, b_re, b_im)

    got = jax.jit(jax.grad(lambda *args: loss(complex_affine_scan, *args), argnums=(0, 1, 2)))(a, b, x0)
    want = jax.grad(lambda *args: loss(by_autodiff, *args), argnums=(0, 1, 2))(a, b, x0)
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        assert jnp.allclose(g, w, atol=1e-4, rtol=1e-4)
    assert all(float(jnp.abs(g).max()) > 0 for g in jax.tree.leaves(got))


class _Leaky(GRU):
    """A GRU that ignores episode starts: its carry leaks from one episode into the next."""

    def __call__(self, carry, xs, starts):
        return super().__call__(carry, xs, jnp.zeros_like(starts))


class _ResetsPerCall(GRU):
    """Resets at the first step of every call: fine over one sequence, wrong one step at a time."""

    def __call__(self, carry, xs, starts):
        return super().__call__(carry, xs, starts.at[0].set(True))


class _ResetsElsewhere(GRU):
    """Resets to zeros, but a fresh episode's carry (`init_carry()`) is not zeros."""

    def init_carry(self):
        return jnp.full((self.out_size,), 0.5, jnp.float32)


class _GradientLeaks(GRU):
    """The GRU's values, but every output has a gradient with respect to every earlier input, across starts."""

    def __call__(self, carry, xs, starts):
        carry, ys = super().__call__(carry, xs, starts)
        past = jnp.cumsum(jnp.sum(xs, axis=1))
        return carry, ys + (past - jax.lax.stop_gradient(past))[:, None]


class _Permuted(GRU):
    """A correct cell with an integer array field (an index table), which has no gradient."""

    perm: jax.Array

    def __init__(self, in_size, hidden_size, *, key):
        super().__init__(in_size, hidden_size, key=key)
        self.perm = jnp.arange(hidden_size)[::-1]

    def __call__(self, carry, xs, starts):
        carry, ys = super().__call__(carry, xs, starts)
        return carry, ys[:, self.perm]


class _DebouncedReset(AbstractMemory):
    """Skips the reset at a start right after another start: a one-step episode leaks into the next one (the check
    looked from each environment's first and last start only)."""

    proj: Dense
    in_size: int = eqx.field(static=True)
    out_size: int = eqx.field(static=True)

    def __init__(self, in_size, hidden_size, *, key):
        self.in_size, self.out_size = in_size, hidden_size
        self.proj = Dense(in_size, hidden_size, key=key)

    def init_carry(self):
        return jnp.zeros(self.out_size), jnp.zeros((), bool)

    def __call__(self, carry, xs, starts):
        def step(c, inp):
            (h, prev), (u, s) = c, inp
            h = 0.5 * jnp.where(s & ~prev, 0.0, h) + u
            return (h, s), h

        return jax.lax.scan(step, carry, (jnp.tanh(self.proj(xs)), starts))


@pytest.mark.slow
def test_check_memory_catches_broken_cells():
    with pytest.raises(AssertionError, match=r"check_memory\(_Leaky\): .*information crosses an episode start"):
        check_memory(_Leaky(IN, H, key=jax.random.key(0)))
    with pytest.raises(AssertionError, match=r"information crosses an episode start: on environment \d, the outputs "
                                             r"from the start at step 2"):
        check_memory(_DebouncedReset(IN, H, key=jax.random.key(0)))
    with pytest.raises(AssertionError, match="one step at a time differs from one call over the sequence"):
        check_memory(_ResetsPerCall(IN, H, key=jax.random.key(0)))
    with pytest.raises(AssertionError, match=r"differ from a fresh cell's \(init_carry\(\)\)"):
        check_memory(_ResetsElsewhere(IN, H, key=jax.random.key(0)))
    with pytest.raises(AssertionError, match="have gradient .* with respect to inputs before it"):
        check_memory(_GradientLeaks(IN, H, key=jax.random.key(0)))
    check_memory(_Permuted(IN, H, key=jax.random.key(0)))  # integer leaves are fine: not differentiated

    class NotStatic(LSTM):
        width: int  # a hyperparameter as an ordinary field: not an array, so not vmappable

        def __init__(self, in_size, hidden_size, *, key):
            super().__init__(in_size, hidden_size, key=key)
            self.width = hidden_size

    with pytest.raises(AssertionError, match=r"field \.width is a int, not an array.*static=True"):
        check_memory(NotStatic(IN, H, key=jax.random.key(0)))
    with pytest.raises(AssertionError, match="must subclass pobax.memory.AbstractMemory"):
        check_memory(eqx.nn.GRUCell(IN, H, key=jax.random.key(0)))
    check_memory(GRU(IN, H, key=jax.random.key(0)))  # and the real GRU passes


CELL = '''
import equinox as eqx, jax, jax.numpy as jnp
from pobax.memory import AbstractMemory, Dense

class Trace(AbstractMemory):
    proj: Dense
    decay: jax.Array
    in_size: int = eqx.field(static=True)
    out_size: int = eqx.field(static=True)

    def __init__(self, in_size, hidden_size, *, key):
        self.in_size, self.out_size = in_size, hidden_size
        self.proj, self.decay = Dense(in_size, hidden_size, key=key), jnp.full(hidden_size, 0.9)

    def init_carry(self):
        return jnp.zeros(self.out_size)

    def __call__(self, carry, xs, starts):
        def step(h, inp):
            h = self.decay * jnp.where(inp[1], 0.0, h) + jnp.tanh(inp[0])
            return h, h
        return jax.lax.scan(step, carry, (self.proj(xs), starts))

NotAMemory = eqx.nn.Linear

class OtherSignature(Trace):
    def __init__(self, hidden_size, *, key):
        super().__init__(hidden_size, hidden_size, key=key)
'''
TINY = ["--env", "tmaze_3", "--hidden-size", "8", "--num-envs", "2", "--num-minibatches", "2", "--num-steps", "16",
        "--total-steps", "64", "--num-seeds", "2", "--num-chunks", "2", "--fast-compile", "--quiet"]


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """A user's module `my_cells` in the current directory (not on sys.path: found as `python -m` would)."""
    (tmp_path / "my_cells.py").write_text(textwrap.dedent(CELL))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    yield tmp_path
    sys.modules.pop("my_cells", None)


@pytest.mark.slow
def test_user_cell_trains_from_the_cli_resumes_and_rebuilds(user_module, capsys):
    out = user_module / "run"
    cli.main(["train", *TINY, "--memory", "my_cells:Trace", "--out", str(out), "--max-chunks", "1"])
    assert "stopped after --max-chunks" in capsys.readouterr().out
    saved = json.loads((out / "config.json").read_text())["config"]
    assert saved["memory"] == "my_cells:Trace"
    cfg = config_from_dict(saved)
    assert cfg.memory == "my_cells:Trace" and json.loads(json.dumps(saved)) == saved
    cli.main(["train", "--resume", str(out), "--quiet"])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["finished"] and len(summary["sets"][0]["disc_return"]["per_seed"]) == 2
    like = Runs(cfg).template().model  # the model rebuilt from config.json: the user's class
    model = eqx.tree_deserialise_leaves(out / "model.eqx", like)  # with the trained parameters
    assert type(model.memory).__name__ == "Trace" and model.memory.decay.shape == (2, 8)
    assert not jnp.allclose(model.memory.proj.weight[0], model.memory.proj.weight[1])  # one cell per seed
    # the same string in a preset file (as `sweep` writes them)
    (user_module / "preset.json").write_text(json.dumps({"preset": {"memory": "my_cells:Trace", "lr": 1e-3}}))
    from_file = apply_preset(TrainConfig(), load_preset(user_module / "preset.json"))
    assert from_file.memory == "my_cells:Trace" and from_file.lr == (1e-3,)
    validate(from_file)


@pytest.mark.parametrize("spec, message", [
    ("lstmm", "Unknown memory 'lstmm': the built-in memories are memoryless, gru, trxl, lstm, lru, s6, ffm"),
    ("no_such_module:Cell", "cannot import 'no_such_module'"),
    ("my_cells:Missing", "module 'my_cells' has no attribute 'Missing'"),
    ("my_cells:NotAMemory", "NotAMemory is not a subclass of pobax.memory.AbstractMemory"),
    ("my_cells:", "is not of the form package.module:ClassName"),
    ("my_cells:OtherSignature", "pobax builds it as OtherSignature(in_size, hidden_size, key=key)"),
])
def test_bad_memory_specs_are_one_line_errors_before_anything_runs(user_module, capsys, spec, message):
    for argv in (["train", *TINY, "--memory", spec, "--out", "r"],
                 ["gap", *TINY, "--agents", "floor", "--memories", spec, "--out", "g"],
                 ["benchmark", "--envs", "tmaze_10", "--budget", "smoke", "--memories", spec, "--out", "b"]):
        with pytest.raises(SystemExit) as e:
            cli.main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and message in err and err.strip().count("\n") == 0, (argv, err)
    assert not any((user_module / d).exists() for d in ("r", "g", "b"))  # nothing was written
    with pytest.raises(ConfigError, match=re.escape(message)):
        validate(TrainConfig(memory=spec))


@pytest.mark.slow
def test_zoo_and_user_memories_join_the_gap_and_the_benchmark(user_module, capsys):
    memories = (*ZOO, "my_cells:Trace")
    cli.main(["benchmark", "--envs", "tmaze_10", "battleship_10", "--budget", "smoke", "--agents", "gru",
              "--memories", *memories, "--dry-run", "--out", "b"])
    printed = capsys.readouterr().out
    assert all(f"{m} (partial)" in printed for m in memories)
    plan = benchmark_plan(("tmaze_10", "battleship_10"), "smoke", agents=("gru",), memories=memories)
    for env in ("tmaze_10", "battleship_10"):
        for e in [e for e in plan if e.env == env]:
            assert e.config.memory == e.agent.name
            # a memory's own row where the registry has one (found by a sweep), else the GRU's preset
            row = paper_preset(env, e.agent.name if e.agent.name in spec(env).best else "gru")
            for k in ("lr", "lambda0", "action_concat"):
                assert getattr(e.config, k) == row.get(k, getattr(TrainConfig(), k)), (env, e.agent.name, k)
    assert paper_preset("tmaze_10", "lru")["lambda0"] == (0.1,) != paper_preset("tmaze_10", "gru")["lambda0"]
    assert paper_preset("battleship_10", "lru")["lambda0"] == (0.9,) != paper_preset("battleship_10", "gru")["lambda0"]
    assert paper_preset("battleship_10", "lstm")["lr"] == (2.5e-4,) != paper_preset("battleship_10", "gru")["lr"]
    assert paper_preset("battleship_10", "my_cells:Trace") == paper_preset("battleship_10", "gru")  # no row of its own
    cli.main(["gap", *TINY, "--agents", "floor", "--memories", "lstm", "my_cells:Trace", "--out", "g"])
    printed = capsys.readouterr().out
    report = json.loads((user_module / "g" / "gap.json").read_text())
    assert [a["name"] for a in report["agents"]] == ["floor", "lstm", "my_cells:Trace"]
    assert "my_cells:Trace (partial)" in printed and (user_module / "g" / "my_cells:Trace" / "model.eqx").exists()
