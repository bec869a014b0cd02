"""Micro-benchmark of the GRU recurrence alone (the time loop of `pobax.memory.GRU`), as PPO's replay runs it.

    python benchmarks/bench_gru_kernel.py                                   # default shapes, dot / reduce / fused
    python benchmarks/bench_gru_kernel.py --shapes 30x4x128x32 --num-warps 1 2 4 8 --iters 200
    python benchmarks/bench_gru_kernel.py --shapes 1x8x128x512 --impls dot dot_ad reduce reduce_ad   # the backward
    python benchmarks/bench_gru_kernel.py --iters 2                         # CPU smoke run (fused is interpreted)

A shape is SEEDSxENVSxTxH: the recurrence of T steps and hidden size H over ENVS sequences (vmapped, weights shared,
time-major inputs as in PPO's minibatches) and SEEDS runs (vmapped, weights batched). The implementations are those
of `GRU(impl=...)`: `dot` and `reduce` (`pobax.memory._gru.scan_recurrence(impl=..., vjp="manual")`, the scan with
the library's hand-written backward; `dot_ad` / `reduce_ad` the same scan with JAX's own backward, `vjp="autodiff"`),
`fused` (one Pallas kernel per direction, `pobax.memory._gru_fused.fused_recurrence`, only where
`fused_supported(T, H)`; one row per `--num-warps` value) and `auto` (what `GRU(impl="auto")` picks for H on this
backend, `pobax._backend.gru_impl`). Each is timed forward and forward + backward (`jax.grad` of the sum of the
outputs w.r.t. the weights, bias, input projections and carry), jitted, after compiling and `--warmup` calls, as µs
per call (mean over `--iters` calls, then `block_until_ready`) and µs per time step. Every implementation is checked
against dot (max |Δ| of the outputs and of the gradients, relative to the largest value of each array). Prints the
device and the JAX version.
"""

import argparse
import functools
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from pobax._cli.args import ScriptParser
from pobax._backend import default_unroll, gru_impl, platform_of
from pobax.memory._gru import scan_recurrence as _scan_recurrence
from pobax.memory._gru_fused import fused_recurrence, fused_supported


GPU_SHAPES = ["30x1x128x32", "30x4x128x32", "30x4x128x64", "30x4x128x128", "1x8x128x256", "1x32x128x512"]
CPU_SHAPES = ["30x1x128x32", "30x4x128x32", "4x4x128x64", "1x4x128x128"]


def scan_recurrence(impl: str, unroll: int):
    """The recurrence exactly as `GRU.__call__` runs it (`impl` "dot" or "reduce"; with the suffix "_ad", its
    gradient by JAX's transpose of the scan, `vjp="autodiff"`, instead of the library's hand-written backward)."""
    base, _, ad = impl.partition("_")
    return functools.partial(_scan_recurrence, impl=base, unroll=unroll, vjp="autodiff" if ad else "manual")


def batched(f):
    """Seeds (weights batched) × environments (weights shared; inputs time-major, as PPO's minibatches)."""
    inner = jax.vmap(f, in_axes=(None, None, 1, 1, 0), out_axes=(0, 1))
    return jax.vmap(inner)


def make_inputs(seeds: int, envs: int, t: int, h: int, key):
    ks = jax.random.split(key, 5)
    w = jax.random.normal(ks[0], (seeds, 3 * h, h)) / np.sqrt(h)
    b = 0.1 * jax.random.normal(ks[1], (seeds, h))
    gx = jax.random.normal(ks[2], (seeds, t, envs, 3 * h))
    starts = jax.random.bernoulli(ks[3], 0.02, (seeds, t, envs)).at[:, t // 2].set(True)
    carry = 0.5 * jax.random.normal(ks[4], (seeds, envs, h))
    return w, b, gx, starts, carry


def timed(fn, args, warmup: int, iters: int):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    for _ in range(warmup):
        out = jax.block_until_ready(fn(*args))
    t0 = time.perf_counter()
    for _ in range(iters):
        out = fn(*args)
    out = jax.block_until_ready(out)
    return out, (time.perf_counter() - t0) / iters * 1e6, compile_s


def max_diff(a, b):
    """Largest |a − b| over all leaves, each relative to the largest |b| of its leaf."""
    return max(float(jnp.max(jnp.abs(x - y)) / jnp.maximum(jnp.max(jnp.abs(y)), 1e-30))
               for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def main():
    p = ScriptParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--shapes", nargs="+", default=None,
                   help="SEEDSxENVSxTxH (default: " + " ".join(GPU_SHAPES) + "; on the CPU " + " ".join(CPU_SHAPES)
                   + ", as reduce's backward takes minutes there at H = 512)")
    p.add_argument("--impls", nargs="+", default=["dot", "reduce", "fused"],
                   choices=["auto", "dot", "reduce", "dot_ad", "reduce_ad", "fused"],
                   help="dot / reduce: the scan (hand-written backward); *_ad: the same with JAX's autodiff backward; "
                        "fused: the Pallas kernels; auto: the library's choice for H on this backend")
    p.add_argument("--num-warps", type=int, nargs="+", default=[0],
                   help="Triton warps for fused (0: the library's choice by hidden size); one row each")
    p.add_argument("--num-stages", type=int, default=None, help="Triton pipelining stages for fused")
    p.add_argument("--unroll", type=int, default=None,
                   help="scan unroll for dot/reduce (default: the library's, 1 on CPU and 4 on GPU)")
    p.add_argument("--iters", type=int, default=50)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--json", default=None)
    args = p.parse_args()
    platform = platform_of()
    cpu = platform == "cpu"
    unroll = args.unroll or default_unroll(platform)
    shapes = args.shapes or (CPU_SHAPES if cpu else GPU_SHAPES)
    device = f"{jax.devices()[0].device_kind} ({platform})"
    print(f"device: {device}, jax {jax.__version__}, scan unroll {unroll}, iters {args.iters}"
          + (" (fused runs in Pallas interpret mode on the CPU)" if cpu else ""))
    print(f"{'shape SxExTxH':16s} {'impl':12s} {'fwd µs':>11s} {'fwd+bwd µs':>11s} {'fwd µs/step':>11s} "
          f"{'f+b µs/step':>11s} {'compile s':>9s} {'rel Δ out':>10s} {'rel Δ grad':>11s}")
    rows = []
    for shape in shapes:
        seeds, envs, t, h = (int(v) for v in shape.split("x"))
        inputs = make_inputs(seeds, envs, t, h, jax.random.key(0))
        variants = []
        for impl in args.impls:
            if impl == "auto":
                impl = gru_impl(h, platform)
                print(f"{shape:16s} auto = {impl}")
                if impl in [i for i in args.impls if i != "auto"]:
                    continue
            if impl != "fused":
                variants.append((impl, scan_recurrence(impl, unroll)))
            elif fused_supported(t, h):
                for nw in args.num_warps:
                    name = "fused" if nw == 0 else f"fused w={nw}"
                    variants.append((name, lambda *a, nw=nw: fused_recurrence(
                        *a, num_warps=nw or None, num_stages=args.num_stages, interpret=platform != "gpu")))
            else:
                print(f"{shape:16s} {'fused':12s} {'n/a (fused_supported is False)':>30s}")
        reference = None
        for name, f in variants:
            fwd = jax.jit(batched(f))

            def loss(w, b, gx, starts, carry, f=f):
                return jnp.sum(batched(f)(w, b, gx, starts, carry)[1])

            fwdbwd = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 4)))
            try:
                out, fwd_us, c1 = timed(fwd, inputs, args.warmup, args.iters)
                grads, fb_us, c2 = timed(fwdbwd, inputs, args.warmup, args.iters)
            except Exception as e:  # e.g. a kernel that fails to compile: report it and go on with the others
                print(f"{shape:16s} {name:12s} FAILED: {type(e).__name__}: {str(e)[:2000]}", flush=True)
                continue
            if reference is None and name == "dot":
                reference = (out, grads)
            elif reference is None:  # no dot row yet: compare with dot
                dot = batched(scan_recurrence("dot", unroll))
                reference = (jax.jit(dot)(*inputs), jax.jit(jax.grad(
                    lambda *a: jnp.sum(dot(*a)[1]), argnums=(0, 1, 2, 4)))(*inputs))
            d_out = max_diff(out, reference[0]) if reference is not None and name != "dot" else float("nan")
            d_grad = max_diff(grads, reference[1]) if reference is not None and name != "dot" else float("nan")
            print(f"{shape:16s} {name:12s} {fwd_us:11.1f} {fb_us:11.1f} {fwd_us / t:11.3f} {fb_us / t:11.3f} "
                  f"{c1 + c2:9.1f} {d_out:10.2e} {d_grad:11.2e}", flush=True)
            rows.append(dict(shape=shape, seeds=seeds, envs=envs, time=t, hidden=h, impl=name, fwd_us=fwd_us,
                             fwd_bwd_us=fb_us, compile_s=c1 + c2, rel_diff_out=d_out, rel_diff_grad=d_grad,
                             device=device, jax=jax.__version__, unroll=unroll))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)


if __name__ == "__main__":
    main()
