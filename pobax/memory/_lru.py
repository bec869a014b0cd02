"""Linear recurrent unit in real arithmetic: `Dense(in, h) → ReLU → LRU`, replayed by one associative scan.

Orvieto, Smith, Gu, Fernando, Gulcehre, Pascanu & De, "Resurrecting Recurrent Neural Networks for Long Sequences",
ICML 2023 (arXiv:2303.06349). The state is `hidden_size` complex units `x_t = λ ⊙ x_{t−1} + γ ⊙ (B u_t)`, the output
`y_t = Re(C x_t) + D ⊙ u_t`, with `λ = exp(−exp(ν) + i·exp(θ))` (|λ| < 1 by construction) and the normalisation
`γ = sqrt(1 − |λ|²)`. Initialisation as the paper's: |λ| uniform on the ring [0, 1] (ν), phase uniform in
[0, 2π) (θ), `B` normal with variance 1/(2h), `C` normal with variance 1/h, `D` standard normal.

Every complex number is held as its real and imaginary parts and every product written out, and the scan's operator
works on real arrays. The input and output projections are one real matrix product each, `u @ [B_re; B_im]ᵀ` and
`[x_re, x_im] @ [C_re, −C_im]ᵀ` (one product each instead of two: fewer, larger kernels; docs/memories.md). An
episode start zeroes the decay of its step (`a_t = 0`): the state before it is forgotten, which is the reset of the
contract (pobax/memory/_base.py). The carry is the state `(re, im)`; the carry given is folded into the first step.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from ._base import AbstractMemory, check_inputs
from ._layers import MLP, flat_draw, matmul_t

LRUCarry = tuple[Float[Array, " hidden"], Float[Array, " hidden"]]  # the complex state: (real, imaginary)


def _combine(first, second):
    """The scan's operator on (decay, state) pairs, complex numbers as (re, im): `(a₁, b₁) ∘ (a₂, b₂) = (a₂ a₁,
    a₂ b₁ + b₂)`, the affine map `x ↦ a x + b` applied first by the first element."""
    (a1r, a1i, b1r, b1i), (a2r, a2i, b2r, b2i) = first, second
    return (a2r * a1r - a2i * a1i, a2r * a1i + a2i * a1r,
            a2r * b1r - a2i * b1i + b2r, a2r * b1i + a2i * b1r + b2i)


def _scan(a_re, a_im, b_re, b_im):
    _, _, x_re, x_im = jax.lax.associative_scan(_combine, (a_re, a_im, b_re, b_im))
    return x_re, x_im


@jax.custom_vjp
def _recurrence(a_re, a_im, b_re, b_im):
    """`x_t = a_t x_{t−1} + b_t` from `x_{−1} = 0` along axis 0, complex numbers as (re, im)."""
    return _scan(a_re, a_im, b_re, b_im)


def _recurrence_fwd(a_re, a_im, b_re, b_im):
    x_re, x_im = _scan(a_re, a_im, b_re, b_im)
    return (x_re, x_im), (a_re, a_im, x_re, x_im)


def _recurrence_bwd(res, g):
    """The adjoint recurrence, another associative scan, run backwards in time: `λ_t = g_t + conj(a_{t+1}) λ_{t+1}`,
    then `∂b_t = λ_t` and `∂a_t = λ_t conj(x_{t−1})` (the cotangents of the real and imaginary parts, as a real loss
    has them). Differentiating through `associative_scan` instead transposes every level of its tree of slices; this
    backward costs about one more scan (faster LRU training on the CPU: `python benchmarks/bench_train.py --cases
    tmaze_10:lru:30`; docs/memories.md)."""
    a_re, a_im, x_re, x_im = res
    g_re, g_im = g

    def shift(v):  # v_{t+1}, zero past the end
        return jnp.concatenate([v[1:], jnp.zeros_like(v[:1])])

    lam_re, lam_im = _scan(*(jnp.flip(v, 0) for v in (shift(a_re), -shift(a_im), g_re, g_im)))
    lam_re, lam_im = jnp.flip(lam_re, 0), jnp.flip(lam_im, 0)
    xp_re = jnp.concatenate([jnp.zeros_like(x_re[:1]), x_re[:-1]])  # x_{t−1}, zero before the first step
    xp_im = jnp.concatenate([jnp.zeros_like(x_im[:1]), x_im[:-1]])
    return (lam_re * xp_re + lam_im * xp_im, lam_im * xp_re - lam_re * xp_im, lam_re, lam_im)


_recurrence.defvjp(_recurrence_fwd, _recurrence_bwd)


def complex_affine_scan(
    a: tuple[Float[Array, "time *n"], Float[Array, "time *n"]],
    b: tuple[Float[Array, "time *n"], Float[Array, "time *n"]],
    x0: tuple[Float[Array, " *n"], Float[Array, " *n"]],
) -> tuple[Float[Array, "time *n"], Float[Array, "time *n"]]:
    """Every state `x_t = a_t x_{t−1} + b_t` from `x0`, complex numbers as (re, im) pairs of real arrays, by one
    associative scan (and one more, backwards, for the gradient). `a_t = 0` forgets the state before step t (an
    episode start)."""
    (a_re, a_im), (b_re, b_im), (x0_re, x0_im) = a, b, x0
    # x0 enters through the first step: b₀ += a₀ x0
    b_re = b_re.at[0].add(a_re[0] * x0_re - a_im[0] * x0_im)
    b_im = b_im.at[0].add(a_re[0] * x0_im + a_im[0] * x0_re)
    return _recurrence(a_re, a_im, b_re, b_im)


class LRU(AbstractMemory[LRUCarry]):
    """Linear recurrent unit: Orvieto et al., "Resurrecting Recurrent Neural Networks for Long Sequences", ICML 2023
    (arXiv:2303.06349). `Dense(in, h) → ReLU`, then the diagonal complex recurrence `x_t = λ ⊙ x_{t−1} + γ ⊙ (B u_t)`
    and `y_t = Re(C x_t) + D ⊙ u_t` with `h` complex units, in real arithmetic; replay is an associative scan."""

    pre: MLP
    nu_log: Float[Array, " hidden"]
    theta_log: Float[Array, " hidden"]
    gamma_log: Float[Array, " hidden"]
    b_re: Float[Array, "hidden hidden"]
    b_im: Float[Array, "hidden hidden"]
    c_re: Float[Array, "hidden hidden"]
    c_im: Float[Array, "hidden hidden"]
    d: Float[Array, " hidden"]
    in_size: int = eqx.field(static=True)
    out_size: int = eqx.field(static=True)

    def __init__(self, in_size: int, hidden_size: int, *, key: PRNGKeyArray, r_min: float = 0.0,
                 r_max: float = 1.0, max_phase: float = 2 * math.pi):
        k_pre, k_r, k_p, k_bre, k_bim, k_cre, k_cim, k_d = jax.random.split(key, 8)
        h = hidden_size
        self.in_size, self.out_size = in_size, h
        self.pre = MLP((in_size, h), key=k_pre)
        u1, u2 = jax.random.uniform(k_r, (h,)), jax.random.uniform(k_p, (h,))
        self.nu_log = jnp.log(-0.5 * jnp.log(u1 * (r_max**2 - r_min**2) + r_min**2))
        self.theta_log = jnp.log(max_phase * u2)
        self.gamma_log = 0.5 * jnp.log(1.0 - jnp.exp(-2.0 * jnp.exp(self.nu_log)))  # log sqrt(1 − |λ|²)
        self.b_re = flat_draw(jax.random.normal, k_bre, (h, h)) / math.sqrt(2 * h)
        self.b_im = flat_draw(jax.random.normal, k_bim, (h, h)) / math.sqrt(2 * h)
        self.c_re = flat_draw(jax.random.normal, k_cre, (h, h)) / math.sqrt(h)
        self.c_im = flat_draw(jax.random.normal, k_cim, (h, h)) / math.sqrt(h)
        self.d = jax.random.normal(k_d, (h,))

    def init_carry(self) -> LRUCarry:
        return jnp.zeros((self.out_size,), jnp.float32), jnp.zeros((self.out_size,), jnp.float32)

    def __call__(
        self, carry: LRUCarry, xs: Float[Array, "time in_size"], starts: Bool[Array, " time"]
    ) -> tuple[LRUCarry, Float[Array, "time out_size"]]:
        check_inputs(self, xs, starts)
        u = jax.nn.relu(self.pre(xs))
        gamma = jnp.exp(self.gamma_log)[None]
        h = self.out_size
        bu = matmul_t(u, jnp.concatenate([self.b_re, self.b_im], 0))  # (time, 2h): B_re u, then B_im u
        bu_re, bu_im = gamma * bu[:, :h], gamma * bu[:, h:]
        modulus, phase = jnp.exp(-jnp.exp(self.nu_log))[None], jnp.exp(self.theta_log)[None]
        keep = jnp.where(starts, 0.0, 1.0)[:, None]  # an episode start forgets the state before it
        a_re, a_im = keep * (modulus * jnp.cos(phase)), keep * (modulus * jnp.sin(phase))
        x_re, x_im = complex_affine_scan((a_re, a_im), (bu_re, bu_im), carry)
        ys = matmul_t(jnp.concatenate([x_re, x_im], -1), jnp.concatenate([self.c_re, -self.c_im], 1))  # Re(C x)
        ys = ys + self.d[None] * u
        return (x_re[-1], x_im[-1]), ys
