"""An environment given to `train(env=...)` instead of the configuration's registered one: what a run directory
records of it, how a resume and `load_run` check the environment given then, and how listings, figures and
evaluations name it."""

import dataclasses
import hashlib

import jax
import numpy as np


def given_env_record(env) -> dict:
    """What config.json records of an environment given to `train(env=...)`: its classes ("AutoReset(MyEnv)", for
    listings and figures) and a digest of its classes and parameters (`env_digest`), which a resume and `load_run`
    check the environment given then against."""
    return {"env_given": f"{type(env).__name__}({type(env.unwrapped).__name__})", "env_given_digest": env_digest(env)}


def env_digest(env) -> str:
    """sha256 of an environment's classes and parameters, wrappers included: every field, recursively; arrays by
    dtype, shape and bytes, numbers and strings by value, anything else (a function, say) by its type alone, so the
    digest is the same in every process and on every device."""
    h = hashlib.sha256()

    def walk(x) -> None:
        if dataclasses.is_dataclass(x) and not isinstance(x, type):  # an equinox Module is a dataclass
            h.update(f"<{type(x).__module__}.{type(x).__qualname__}>".encode())
            for f in dataclasses.fields(x):
                h.update(f"{f.name}=".encode())
                walk(getattr(x, f.name, None))
        elif isinstance(x, (jax.Array, np.ndarray, np.generic)):
            a = np.asarray(jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x)
            h.update(f"{a.dtype}{a.shape}".encode() + np.ascontiguousarray(a).tobytes())
        elif isinstance(x, (list, tuple)):
            h.update(f"{type(x).__name__}{len(x)}".encode())
            for y in x:
                walk(y)
        elif isinstance(x, dict):
            h.update(f"dict{len(x)}".encode())
            for k in sorted(x, key=repr):
                h.update(repr(k).encode())
                walk(x[k])
        elif x is None or isinstance(x, (bool, int, float, complex, str, bytes)):
            h.update(repr(x).encode())
        else:  # a function or another object: its repr may hold an address, which differs between processes
            h.update(f"<{type(x).__module__}.{type(x).__qualname__}>".encode())

    walk(env)
    return h.hexdigest()


def given_env_mismatch(record: dict, env) -> str | None:
    """What differs between how a run directory's run was trained (config.json: `env_given` names the environment
    passed to `train(env=...)`, absent for cfg.env's registered one; `env_given_digest` its parameters) and the `env`
    given now (None: the registered one); None where they agree."""
    given = record.get("env_given") if isinstance(record, dict) else None
    if given is not None and env is None:
        return f"trained in an environment given to train(env=...) ({given}), not {record['config'].get('env')!r}'s " \
               f"registered one"
    if given is None and env is not None:
        return "trained in its registered environment, not one given as env=..."
    if given is not None:
        now = given_env_record(env)
        if now["env_given"] != given:
            return f"trained in {given}, not in the {now['env_given']} given now"
        digest = record.get("env_given_digest")  # (runs written before it was recorded: the classes alone)
        if digest is not None and digest != now["env_given_digest"]:
            return f"trained in {given} with parameters other than those of the one given now"
    return None


def trained_env(record: dict) -> tuple[str, str]:
    """The environment a run directory's run trained in and its observability, for its listing and figures
    (config.json as `record`): its configuration's, or, for an environment given to `train(env=...)`, its classes
    ("AutoReset(MyEnv)") and "given": the ID and observability its configuration keeps are not what it trained in."""
    given, cfg = record.get("env_given"), record["config"]
    return (str(cfg.get("env")), str(cfg.get("observability"))) if given is None else (str(given), "given")
