"""Dead units: how many ReLU units of a trained memoryless agent's MLP still fire, against its initialisation.

    python benchmarks/relu_activity.py runs/maze02-ceiling runs/maze01-ceiling
    python benchmarks/relu_activity.py runs/x --num-obs 4096 --json activity.json

For each run directory (`pobax train --memory memoryless`; the first run of its seeds), the observations of
`--num-obs` environment resets (the run's observability) go through the encoder and the memoryless MLP; per layer,
before its ReLU: the share of units active on at least one observation (`alive`: a unit active on none gets no
gradient and stays dead), the mean share active per observation, and the mean pre-activation; and the spread of the
policy's logits across observations (0: the policy ignores its input). The same network at its initialisation (the
run's configuration and seed) is the baseline. Observation normalisation, where the run used it, is applied.
"""

import argparse
import json

import jax

import pobax
from pobax.eval._load import LoadedRun


def activity(model, obs) -> dict:
    h = jax.vmap(model.encoder)(pobax.env.observation_array(obs))
    layers = {}
    for i, layer in enumerate(model.memory.mlp.layers):
        h = layer(h)
        layers[f"dense{i}"] = {"alive": round(float((h > 0).any(0).mean()), 3),
                               "active_per_obs": round(float((h > 0).mean()), 3),
                               "preact_mean": round(float(h.mean()), 3)}
        h = jax.nn.relu(h)
    logits = model.actor(h)
    return {"layers": layers, "logit_std_across_obs": round(float(logits.std(0).mean()), 4)}


def measure(path: str, num_obs: int) -> dict:
    run = pobax.load_run(path)
    if run.config.memory != "memoryless":
        raise SystemExit(f"{path}: memory {run.config.memory!r}; this measures memoryless agents' MLPs only.")
    _, ts = jax.vmap(lambda k: run.env.reset(key=k))(jax.random.split(jax.random.key(1), num_obs))
    obs = ts.obs
    norm = run.pick_obs_norm(index=0)
    if norm is not None:
        obs = norm(obs)
    cfg = run.config
    init = LoadedRun.untrained(cfg).pick(index=0)  # the training loop's own initialisation of the same run
    return {"run": path, "env": cfg.env, "observability": cfg.observability, "encoder": cfg.encoder,
            "lr": list(cfg.lr), "updates": int(run.metrics["update"].max()) + 1 if len(run.metrics) else 0,
            "env_steps": int(run.metrics["env_step"].max()) if len(run.metrics) else 0,
            "trained": activity(run.pick(index=0), obs), "init": activity(init, obs)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", help="run directories of memoryless agents")
    p.add_argument("--num-obs", type=int, default=2048)
    p.add_argument("--json", help="also write the figures here")
    args = p.parse_args()
    out = {"device": str(jax.devices()[0]), "jax": jax.__version__,
           "runs": [measure(r, args.num_obs) for r in args.runs]}
    for r in out["runs"]:
        print(f"{r['run']}: {r['env']} {r['observability']}, encoder {r['encoder']}, lr {r['lr']}, "
              f"{r['updates']} updates")
        for name in r["trained"]["layers"]:
            t, i = r["trained"]["layers"][name], r["init"]["layers"][name]
            print(f"  {name}: alive {i['alive']:.0%} → {t['alive']:.0%}, "
                  f"pre-activation mean {i['preact_mean']:+.2f} → {t['preact_mean']:+.2f}")
        print(f"  logit spread across observations: {r['init']['logit_std_across_obs']} → "
              f"{r['trained']['logit_std_across_obs']}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
