"""Runs sharded over several devices (CPU devices forced in a subprocess) give the results of one device."""

import json
import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import json, sys
    import jax
    from pobax.agent import TrainConfig
    from pobax.eval import train
    cfg = TrainConfig(env="tmaze_5", memory="gru", hidden_size=8, num_envs=4, num_steps=16, num_minibatches=2,
                      total_steps=4 * 16 * 3, num_seeds=3, lr=(2.5e-3, 2.5e-4), num_chunks=1)
    n = int(sys.argv[1])
    r = train(cfg, save=False, progress=False, devices=jax.devices()[:n])
    shardings = {str(x.sharding) for x in jax.tree.leaves(r.state.model)}
    print(json.dumps({"devices": len(jax.devices()), "returns": r.metrics["disc_return"].fillna(-1).tolist(),
                      "losses": r.metrics["pg_loss"].tolist(), "rows": len(r.metrics),
                      "sharded": any("runs" in s for s in shardings)}))
""")


def _run(n: int) -> dict:
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_force_host_platform_device_count=4")
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(n)], env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_sharded_runs_match_one_device():
    one, four = _run(1), _run(4)
    assert four["devices"] == 4 and four["sharded"] and not one["sharded"]
    # 6 runs over 4 devices: padded to 8 and the copies dropped
    assert four["rows"] == one["rows"] == 6 * 3
    assert four["returns"] == one["returns"]
    assert max(abs(a - b) for a, b in zip(four["losses"], one["losses"])) < 1e-5
