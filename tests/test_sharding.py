"""Runs sharded over several devices, and over several processes, give the results of one device (CPU devices
forced in subprocesses; the processes meet through a coordinator on localhost)."""

import json
import os
import socket
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pandas as pd
import pytest

from pobax.agent import TrainConfig
from pobax.eval import gap_report, run_benchmark, sweep

SCRIPT = textwrap.dedent("""
    import json, sys
    args = json.loads(sys.argv[1])
    import jax
    import numpy as np
    import pobax
    if args.get("procs"):
        pobax.init_distributed(f"localhost:{args['port']}", num_processes=args["procs"], process_id=args["pid"])
    from pobax.agent import TrainConfig
    from pobax.eval import train
    cfg = TrainConfig(env="tmaze_5", memory="gru", hidden_size=8, num_envs=4, num_steps=16, num_minibatches=2,
                      total_steps=4 * 16 * 3, num_seeds=3, lr=(2.5e-3, 2.5e-4), num_chunks=3)
    devices = jax.devices()[:args["devices"]] if args.get("devices") else None
    r = train(cfg, args.get("out"), save=bool(args.get("out")), progress=False, devices=devices,
              resume=args.get("resume", False), max_chunks=args.get("max_chunks"))
    shardings = {str(x.sharding) for x in jax.tree.leaves(r.state.model) if isinstance(x, jax.Array)}
    print(json.dumps({"devices": len(jax.devices()), "processes": jax.process_count(),
                      "returns": r.metrics["disc_return"].fillna(-1).tolist(), "losses": r.metrics["pg_loss"].tolist(),
                      "rows": len(r.metrics), "sharded": any("runs" in s for s in shardings),
                      "params": float(sum(np.abs(np.asarray(x)).sum() for x in jax.tree.leaves(r.state.model)
                                          if hasattr(x, "dtype") and jax.numpy.issubdtype(x.dtype, jax.numpy.floating))),
                      "run_dir": str(r.run_dir) if r.run_dir else None}))
""")

ENV = dict(os.environ, JAX_PLATFORMS="cpu")


def _start(args: dict, devices_per_process: int) -> subprocess.Popen:
    env = dict(ENV, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices_per_process}")
    return subprocess.Popen([sys.executable, "-c", SCRIPT, json.dumps(args)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _result(p: subprocess.Popen) -> dict:
    out, err = p.communicate(timeout=900)
    assert p.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


def _run(args: dict, devices_per_process: int = 4) -> dict:
    return _result(_start(args, devices_per_process))


def _two_processes(args: dict) -> list[dict]:
    with socket.socket() as s:  # a free port for the coordinator
        s.bind(("localhost", 0))
        port = s.getsockname()[1]
    procs = [_start(dict(args, procs=2, pid=i, port=port), 2) for i in range(2)]
    return [_result(p) for p in procs]


def _same_run(a: dict, b: dict) -> None:
    assert a["rows"] == b["rows"] == 6 * 3  # 6 runs; on 4 devices padded to 8 and the copies dropped
    assert a["returns"] == b["returns"]
    assert max(abs(x - y) for x, y in zip(a["losses"], b["losses"])) < 1e-5
    assert abs(a["params"] - b["params"]) < 1e-3 * abs(b["params"])


@pytest.mark.slow
def test_sharded_runs_match_one_device():
    one, four = _run({"devices": 1}), _run({"devices": 4})
    assert four["devices"] == 4 and four["sharded"] and not one["sharded"]
    _same_run(four, one)


COLLECTIVES = textwrap.dedent("""
    import re
    import jax
    from pobax.agent import TrainConfig
    from pobax.agent import _train
    # A convolutional encoder (the maze's 2x3 view) batched over runs: left to the compiler's partitioner, the
    # sharded program gathered its weights and activations across the devices (28 all-gathers in this one).
    cfg = TrainConfig(env="Navix-DMLab-Maze-01-v0", memory="memoryless", hidden_size=8, num_envs=2, num_steps=8,
                      num_minibatches=1, update_epochs=1, total_steps=2 * 8, num_seeds=4, num_chunks=1)
    runs = _train.Runs(cfg, jax.devices())
    text = runs.chunk_program().lower(runs.fixed(0), runs._pad(runs.init())).lowered.compile().as_text()
    print(runs.sharding is not None, len(re.findall(r"(all-gather|all-reduce|all-to-all|collective-permute)[-a-z]*\\(", text)))
""")


@pytest.mark.slow
def test_sharded_runs_never_meet():
    """Each device trains its own runs: the sharded chunk program has no collective operation."""
    pytest.importorskip("navix")
    env = dict(ENV, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    out = subprocess.run([sys.executable, "-c", COLLECTIVES], env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    sharded, collectives = out.stdout.split()
    assert sharded == "True" and collectives == "0"


@pytest.mark.slow
def test_two_processes_match_one_process_and_resume_across_layouts(tmp_path):
    ref = _run({"devices": 1, "out": str(tmp_path / "one")}, 1)
    # chunk 1 in two processes × two devices (the 6 runs over 4 devices of 2 processes; process 0 alone writes the
    # run directory), chunk 2 in one process on one device, chunk 3 in two processes again: the same run
    split = str(tmp_path / "two")
    lead, other = _two_processes({"out": split, "max_chunks": 1})
    assert lead["processes"] == other["processes"] == 2 and lead["devices"] == 4
    assert lead["run_dir"] == split and other["run_dir"] is None
    assert json.loads((tmp_path / "two" / "checkpoint.json").read_text())["chunks_done"] == 1
    _run({"devices": 1, "out": split, "resume": True, "max_chunks": 1}, 1)
    assert json.loads((tmp_path / "two" / "checkpoint.json").read_text())["chunks_done"] == 2
    lead, other = _two_processes({"out": split, "resume": True})
    _same_run(lead, ref)
    _same_run(other, ref)  # every process gets every run's metrics and state
    one_csv, two_csv = (pd.read_csv(tmp_path / d / "metrics.csv") for d in ("one", "two"))
    assert list(one_csv.columns) == list(two_csv.columns) and one_csv["disc_return"].equals(two_csv["disc_return"])
    np.testing.assert_allclose(two_csv["v_loss"], one_csv["v_loss"], rtol=1e-4, atol=1e-6)


def test_sweep_gap_and_benchmark_refuse_a_multi_process_run(monkeypatch, tmp_path):
    monkeypatch.setattr(jax, "process_count", lambda: 2)
    for call in (lambda: sweep(TrainConfig(env="tmaze_5"), tmp_path / "s"), lambda: gap_report("tmaze_5", out=tmp_path),
                 lambda: run_benchmark(("tmaze_5",), out=tmp_path / "b")):
        with pytest.raises(ValueError, match="runs in one process"):
            call()
    assert not any(tmp_path.iterdir())  # refused before anything was written
