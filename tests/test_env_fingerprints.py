"""An environment ID never changes behaviour silently.

Every discrete environment of the paper, in each of its observabilities, is played by uniformly random actions from
fixed keys (4 environments × 160 steps, through `make`'s wrappers: time limits and automatic resets included); the
SHA-256 of everything the steps return (observations, rewards, terminations, truncations, final observations) must be
the one in `tests/env_fingerprints.json`. A change to an environment's dynamics, observations, rewards, time limit or
reset distribution fails here. If the change is meant, it is a new behaviour for an old ID: give it a new ID (or an
option whose default keeps the old behaviour), or, for a bug fix, say so in `docs/deviations.md` and write the new
fingerprints with `python tests/test_env_fingerprints.py --write` (the diff names the IDs that changed).

Only environments whose steps are exact (integer grids and boards, a few float operations on rewards) are covered:
the MuJoCo and pixel families' floats depend on the XLA version and the CPU. Two of them, `partial`, run in the default
suite (`DEFAULT`), the others under `-m slow`.
"""

import hashlib
import json
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from pobax.env import make, spec

FILE = Path(__file__).with_name("env_fingerprints.json")
IDS = ("tmaze_10", "rocksample_11_11", "rocksample_15_15", "battleship_10", "Navix-DMLab-Maze-01-v0",
       "Navix-DMLab-Maze-02-v0", "Navix-DMLab-Maze-03-v0")
ENVS, STEPS = 4, 160


def cases() -> list[tuple[str, str]]:
    return [(env_id, obs) for env_id in IDS for obs in spec(env_id).observabilities]


#: In the default suite (`partial`); the rest (3-9 s each on 2 cores) run under `slow`.
DEFAULT = ("tmaze_10", "battleship_10")


def marked(env_id: str, observability: str):
    fast = env_id in DEFAULT and observability == "partial"
    return pytest.param(env_id, observability, marks=() if fast else pytest.mark.slow)


def fingerprint(env_id: str, observability: str, **options) -> str:
    """SHA-256 of a random-action rollout's time steps (dtypes and shapes included); `options`: `make`'s."""
    env = make(env_id, observability=observability, **options)
    n = env.action_space.n

    @jax.jit
    def play(key):
        reset_key, key = jax.random.split(key)
        state, ts = jax.vmap(lambda k: env.reset(key=k))(jax.random.split(reset_key, ENVS))

        def one(state, key):
            action_key, step_key = jax.random.split(key)
            actions = jax.random.randint(action_key, (ENVS,), 0, n)
            state, ts = jax.vmap(lambda s, a, k: env.step(s, a, key=k))(state, actions,
                                                                        jax.random.split(step_key, ENVS))
            return state, (ts.obs, ts.reward, ts.terminated, ts.truncated, ts.final_obs)

        _, steps = jax.lax.scan(one, state, jax.random.split(key, STEPS))
        return (ts.obs,) + steps

    digest = hashlib.sha256()
    for leaf in jax.tree_util.tree_leaves(play(jax.random.key(2020))):
        a = np.asarray(leaf)
        digest.update(f"{a.dtype}{a.shape}".encode())
        digest.update(np.ascontiguousarray(a).tobytes())
    return digest.hexdigest()


@pytest.mark.parametrize("env_id, observability", [marked(*case) for case in cases()])
def test_an_environment_ids_behaviour_is_its_fingerprint(env_id, observability):
    expected = json.loads(FILE.read_text())
    key = f"{env_id}/{observability}"
    assert key in expected, f"no fingerprint for {key}: write them with python tests/test_env_fingerprints.py --write"
    assert fingerprint(env_id, observability) == expected[key], (
        f"{key} no longer plays as it did: a changed environment needs a new ID or option (see this module's "
        f"docstring), or a documented fix and new fingerprints")


def test_the_fingerprint_sees_a_change_of_behaviour():
    """The rollout's hash moves with the environment (another corridor length, another observability, another time
    limit) and stays put for the same one."""
    base = fingerprint("tmaze_10", "partial")
    assert fingerprint("tmaze_9", "partial") != base
    assert fingerprint("tmaze_10", "full") != base
    assert fingerprint("tmaze_10", "partial", time_limit=5) != base
    assert fingerprint("tmaze_10", "partial") == base


if __name__ == "__main__":
    if sys.argv[1:] != ["--write"]:
        sys.exit("usage: python tests/test_env_fingerprints.py --write  (writes tests/env_fingerprints.json)")
    FILE.write_text(json.dumps({f"{e}/{o}": fingerprint(e, o) for e, o in cases()}, indent=1) + "\n")
    print(f"wrote {FILE}")
