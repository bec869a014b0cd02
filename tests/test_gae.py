import jax.numpy as jnp
import numpy as np
import pytest

from pobax.agent import gae


def reference_gae(r, v, nv, term, trunc, gamma, lam):
    """Plain NumPy, one environment, written from the definition."""
    T = len(r)
    adv = np.zeros(T)
    for t in reversed(range(T)):
        delta = r[t] + gamma * (0.0 if term[t] else nv[t]) - v[t]
        cont = 0.0 if (term[t] or trunc[t]) else 1.0
        adv[t] = delta + gamma * lam * cont * (adv[t + 1] if t + 1 < T else 0.0)
    return adv, adv + v


@pytest.mark.parametrize("method", ["weights", "associative", "sequential"])
def test_gae_matches_reference_with_termination_and_truncation(method):
    rng = np.random.default_rng(0)
    T, B = 40, 3
    r = rng.normal(size=(T, B)).astype(np.float32)
    v = rng.normal(size=(T, B)).astype(np.float32)
    nv = np.concatenate([v[1:], rng.normal(size=(1, B))]).astype(np.float32)
    term = rng.random((T, B)) < 0.1
    trunc = (rng.random((T, B)) < 0.1) & ~term
    trunc[5, 0], term[5, 0] = True, False  # at least one of each
    term[9, 1], trunc[9, 1] = True, False
    # at an episode end, next_value is the value of the final observation (not of the next episode's start)
    nv[trunc] = rng.normal(size=trunc.sum())
    adv, tgt = gae(jnp.asarray(r), jnp.asarray(v), jnp.asarray(nv), jnp.asarray(term), jnp.asarray(trunc), 0.99, 0.9,
                   method=method)
    for b in range(B):
        ra, rt = reference_gae(r[:, b], v[:, b], nv[:, b], term[:, b], trunc[:, b], 0.99, 0.9)
        np.testing.assert_allclose(adv[:, b], ra, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(tgt[:, b], rt, rtol=1e-4, atol=1e-4)


def test_truncation_bootstraps_and_termination_does_not():
    r = jnp.array([1.0])
    v = jnp.array([0.0])
    nv = jnp.array([10.0])
    a_trunc, _ = gae(r, v, nv, jnp.array([False]), jnp.array([True]), 0.5, 1.0)
    a_term, _ = gae(r, v, nv, jnp.array([True]), jnp.array([False]), 0.5, 1.0)
    assert float(a_trunc[0]) == 1.0 + 0.5 * 10.0
    assert float(a_term[0]) == 1.0


@pytest.mark.parametrize("lam", [0.0, 0.95, 1.0])
def test_gae_methods_agree_under_vmap_with_traced_lambda(lam):
    """The weighted-sum form (default) against the sequential recursion, with λ an array per run as in training
    (λ = 0 needs 0⁰ = 1 on the diagonal)."""
    import jax

    rng = np.random.default_rng(1)
    R, T, B = 3, 64, 5
    r, v, nv = (jnp.asarray(rng.normal(size=(R, T, B)), jnp.float32) for _ in range(3))
    term = jnp.asarray(rng.random((R, T, B)) < 0.05)
    trunc = jnp.asarray(rng.random((R, T, B)) < 0.05)
    lams = jnp.full((R,), lam, jnp.float32)
    out = {}
    for method in ("weights", "sequential"):
        out[method] = jax.jit(jax.vmap(lambda *a: gae(*a[:5], 0.99, a[5], method=method)))(r, v, nv, term, trunc, lams)
    np.testing.assert_allclose(out["weights"][0], out["sequential"][0], rtol=2e-5, atol=2e-5)
    if lam == 0.0:  # one-step TD errors
        np.testing.assert_allclose(out["weights"][0], r + 0.99 * (1 - term) * nv - v, rtol=1e-6, atol=1e-6)
