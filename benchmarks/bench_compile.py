"""Where the compile time of a training run goes: tracing, lowering to MLIR, XLA compilation, first execution.

    python benchmarks/bench_compile.py --cases tmaze_10:gru:30
    python benchmarks/bench_compile.py --cases tmaze_10:gru:30 --variants default unroll=1 \
        "xla=--xla_gpu_autotune_level=0" --kernels

A case is ENV:MEMORY:SEEDS as in `bench_train.py` (the paper's settings). Every (case, variant) runs in a fresh
Python process, so nothing is cached (the persistent compilation cache is off): what is measured is a cold
start. The run is `pobax.agent.train` with `--updates` updates in 4 chunks; JAX's own compile log
(`jax_log_compiles`) gives, for the two programs of a run — `_init` (network, optimiser, environment reset) and
`_chunk` (the scanned updates) — the seconds spent tracing the Python, converting the jaxpr to MLIR, and in XLA,
and `other` for any other program compiled on the way. `train` compiles the two programs at the same time on
accelerators (`pobax.agent._train.PARALLEL_COMPILE`), so their XLA seconds overlap. `total` = everything a run pays before
steady training, in wall-clock seconds (`TrainResult.compile_s`: both programs compiled, the initialisation run,
and the first chunk beyond a steady one; + any program compiled before that, e.g. by the environment's
construction); this is the figure to compare with the original implementation's compile time, which compiled
initialisation and training as one program.

Variants (space-separated KEY=VALUE, combined with commas): `single=vmap|unbatched` (one run's chunk program traced
under the `vmap` over runs or without it: `pobax.agent._train.SINGLE_RUN_UNBATCHED`), `tiling=N|off`
(`pobax.agent._train.TILING_MAX_HIDDEN`: the widest network whose one run gets a single Triton tiling for every GEMM;
`off`: XLA's autotuning), `dense=N`
(`pobax.memory._layers.REDUCE_MAX_WORK`; `dense=0`: the rollout's dense layers as GEMMs), `cublas=N|off`
(`pobax.agent._train.CUBLAS_MIN_HIDDEN`: the narrowest network whose products over whole sequences go to cuBLAS,
those in sequential loops to Triton; `off`: XLA's default, Triton's GEMMs everywhere), `donate=0` (the chunk
program does not donate the training state),
`gru=dot|reduce|fused|auto`
(`pobax.memory._gru.RECURRENT_IMPL`), `vjp=manual|autodiff` (`SCAN_VJP`), `gae=weights|associative|sequential`,
`unroll=N` (the GRU replay's time-loop unroll), `runroll=N` (the rollout's: `TrainConfig.rollout_unroll`),
`threefry=kernel|xla` (`jax_threefry_gpu_kernel_lowering` for the whole run), `init=kernel|xla` (for the
initialisation only: `pobax.agent._train.INIT_THREEFRY_KERNEL`), `orth=auto|qr|gram_schmidt` (the orthogonal initialisation:
`pobax.memory._layers.ORTHOGONAL_METHOD`), `parallel=1|0` (compile the two programs at the same time or one after
the other: `pobax.agent._train.PARALLEL_COMPILE`), `hidden=N`, `embed=N`, `envs=N` (another environment's network
and batch sizes, to tell the environment's share of the compile from the sizes'), `opts=0` (XLA's own autotuner
settings instead of `pobax.agent._train.GPU_COMPILER_OPTIONS`), `xla=FLAGS` (XLA_FLAGS for the process; last, as it takes the rest of the text). The GEMMs column says how the chunk's GEMMs were placed: "split"
(`CUBLAS_MIN_HIDDEN`), "tiling" (`TILING_MAX_HIDDEN`) or "XLA's" (its autotuning). `--kernels` compiles the chunk program
once more and counts the kernels (fusions and custom calls) of the optimised HLO.
"""

import argparse
import json
import logging
import os
import re
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

STAGES = {"trace": re.compile(r"Finished tracing (?:\+ transforming )?(\w+) for \w+ in ([\d.e-]+) sec"),
          "mlir": re.compile(r"Finished jaxpr to MLIR module conversion \w+\((\w+)\) in ([\d.e-]+) sec"),
          "xla": re.compile(r"Finished XLA compilation of \w+\((\w+)\) in ([\d.e-]+) sec")}


KEYS = ("single", "tiling", "dense", "cublas", "donate", "gru", "vjp", "gae", "unroll", "runroll", "threefry", "init", "orth", "parallel", "hidden", "embed", "envs", "opts", "xla")


def parse_variant(text: str) -> dict:
    out = {}
    if text in ("", "default"):
        return out
    text, _, flags = text.partition("xla=")  # XLA flags may hold commas: `xla=` takes the rest of the text
    if flags:
        out["xla"] = flags
    for part in filter(None, text.rstrip(",").split(",")):
        key, _, value = part.partition("=")
        if key not in KEYS:
            raise SystemExit(f"unknown variant key {key!r} in {text!r}: use one of {', '.join(KEYS)}")
        out[key] = value
    return out


def child(case: str, variant: str, updates: int, kernels: bool) -> dict:
    """Runs in the fresh process: one training run, with JAX's compile log captured."""
    import jax

    jax.config.update("jax_log_compiles", True)
    records: list[str] = []

    class Capture(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())

    logging.getLogger("jax").addHandler(Capture())
    logging.getLogger("jax").propagate = False

    import pobax.agent._gae as gae_mod
    import pobax.agent._train as train_mod
    import pobax.memory._gru as gru_mod
    import pobax.memory._layers as layers_mod
    from bench_train import case_config, parse_case
    from pobax.agent import train

    v = parse_variant(variant)
    gru_mod.RECURRENT_IMPL = v.get("gru", gru_mod.RECURRENT_IMPL)
    gru_mod.SCAN_VJP = v.get("vjp", gru_mod.SCAN_VJP)
    gae_mod.GAE_METHOD = v.get("gae", gae_mod.GAE_METHOD)
    layers_mod.ORTHOGONAL_METHOD = v.get("orth", layers_mod.ORTHOGONAL_METHOD)
    if "dense" in v:
        layers_mod.REDUCE_MAX_WORK = int(v["dense"])
    if "init" in v:
        train_mod.INIT_THREEFRY_KERNEL = v["init"] == "kernel"
    if "threefry" in v:
        jax.config.update("jax_threefry_gpu_kernel_lowering", v["threefry"] == "kernel")
    if "parallel" in v:
        train_mod.PARALLEL_COMPILE = v["parallel"] == "1"
    if "single" in v:
        train_mod.SINGLE_RUN_UNBATCHED = v["single"] == "unbatched"
    if v.get("donate") == "0":
        train_mod._CHUNK._donate = None
    if v.get("opts") == "0":
        train_mod.GPU_COMPILER_OPTIONS = {}
    if "tiling" in v:
        train_mod.TILING_MAX_HIDDEN = None if v["tiling"] == "off" else int(v["tiling"])
    if "cublas" in v:
        train_mod.CUBLAS_MIN_HIDDEN = None if v["cublas"] == "off" else int(v["cublas"])
    chunk_options, decided = train_mod.chunk_options, {}
    train_mod.chunk_options = lambda cfg, runs, jaxpr: decided.setdefault("options", chunk_options(cfg, runs, jaxpr))
    env_id, memory, seeds, grid, obs = parse_case(case)
    sizes = {f: int(v[k]) for k, f in (("hidden", "hidden_size"), ("embed", "embed_size"), ("envs", "num_envs")) if k in v}
    cfg = case_config(env_id, memory, seeds, updates, int(v["unroll"]) if "unroll" in v else None, *obs,
                      rollout_unroll=int(v.get("runroll", 1)), grid=grid, **sizes)
    t0 = time.perf_counter()
    r = train(cfg, save=False, progress=False)
    wall = time.perf_counter() - t0
    stages = {name: {"trace": 0.0, "mlir": 0.0, "xla": 0.0} for name in ("_init", "_chunk", "other")}
    for msg in records:
        for stage, pattern in STAGES.items():
            m = pattern.search(msg)
            if m:
                fn = {"_init_runs": "_init", "_chunk_runs": "_chunk"}.get(m.group(1), "other")
                stages[fn][stage] += float(m.group(2))
    stats = jax.devices()[0].memory_stats() or {}
    row = dict(case=case, variant=variant, device=f"{jax.devices()[0].device_kind} ({jax.default_backend()})",
               jax=jax.__version__, steps_per_s=r.steps_per_s, compile_s=r.compile_s,
               peak_mib=stats["peak_bytes_in_use"] / 2**20 if "peak_bytes_in_use" in stats else None,
               chunk_options=train_mod.compiler_options(decided.get("options")), stages=stages, wall_s=wall,
               total_s=sum(stages["other"].values()) + r.compile_s)
    if kernels:
        import numpy as np

        from pobax.env import make

        env = make(cfg.env, cfg.observability, action_concat=cfg.action_concat)
        state = train_mod._init(cfg, env, train_mod.run_layout(cfg)[1])
        hp = train_mod.run_hyperparams(cfg)
        chunk = train_mod._CHUNK
        key, lowered = chunk.lower(train_mod.structural(cfg), env, state, hp, np.asarray(0, np.int32),
                                   train_mod.chunk_length(cfg))
        chunk.compile(key, lowered)  # a no-op when the run's own executable is still kept
        text = chunk._compiled[key].as_text()
        row["kernels"] = {"fusion": len(re.findall(r"^\s*\S+ = .*\bfusion\(", text, re.M)),
                          "custom-call": len(re.findall(r"^\s*\S+ = .*\bcustom-call\(", text, re.M)),
                          "while": len(re.findall(r"^\s*\S+ = .*\bwhile\(", text, re.M)),
                          "triton_gemm": len(re.findall(r"^\s*\S+ = .*\bfusion\(.*__triton\w*gemm", text, re.M)),
                          "cublas": len(re.findall(r"^\s*\S+ = .*custom_call_target=\"__cublas", text, re.M)),
                          "hlo_lines": text.count("\n")}
    return row


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs="+", default=["tmaze_10:gru:30"])
    p.add_argument("--variants", nargs="+", default=["default"])
    p.add_argument("--updates", type=int, default=40)
    p.add_argument("--kernels", action="store_true")
    p.add_argument("--json", default=None)
    p.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print("ROW " + json.dumps(child(args.child[0], args.child[1], args.updates, args.kernels)), flush=True)
        return
    rows = []
    print(f"{'case':22s} {'variant':34s} {'steps/s':>11s} {'init':>5s} {'trace':>5s} {'mlir':>5s} {'xla':>5s} "
          f"{'other':>6s} {'total':>6s} {'peak MiB':>8s}" + " GEMMs" + (" kernels" if args.kernels else ""), flush=True)
    for case in args.cases:
        for variant in args.variants:
            v = parse_variant(variant)
            env = dict(os.environ, POBAX_COMPILE_CACHE="off")
            if "xla" in v:
                env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + v["xla"]).strip()
            cmd = [sys.executable, os.path.abspath(__file__), "--child", case, variant, "--updates", str(args.updates)]
            out = subprocess.run(cmd + (["--kernels"] if args.kernels else []), env=env, capture_output=True,
                                 text=True)
            line = [ln for ln in out.stdout.splitlines() if ln.startswith("ROW ")]
            if not line:
                print(f"{case:22s} {variant:34s} failed:\n{out.stderr[-2000:]}", flush=True)
                continue
            row = json.loads(line[0][4:])
            rows.append(row)
            s, c = row["stages"], row["stages"]["_chunk"]
            k = row.get("kernels")
            print(f"{case:22s} {variant[:34]:34s} {row['steps_per_s']:11,.0f} {sum(s['_init'].values()):5.1f} "
                  f"{c['trace']:5.1f} {c['mlir']:5.1f} {c['xla']:5.1f} {sum(s['other'].values()):6.1f} {row['total_s']:6.1f}"
                  f" {row['peak_mib'] if row['peak_mib'] is not None else float('nan'):8.0f}"
                  + (" split" if row["chunk_options"].get("xla_gpu_triton_gemm_any") is False else
                     " tiling" if "xla_gpu_gemm_autotuner_override_file" in row["chunk_options"] else " XLA's")
                  + (f" {k['fusion']}f/{k['custom-call']}cc/{k['while']}w, GEMMs {k['triton_gemm']} Triton / {k['cublas']} cuBLAS"
                     if k else ""), flush=True)
    if rows:
        print(f"device: {rows[0]['device']}, jax {rows[0]['jax']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
