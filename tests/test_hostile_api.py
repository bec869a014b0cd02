"""The Python API under a hostile notebook user: values of the wrong kind are refused in a line instead of read as
something else (an action, a flag, a shape), and a run directory is read back only as it trained. Tiny T-Maze runs on
the CPU (`_hostile.py`)."""

import dataclasses
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pobax.agent import ConfigError, gae, policy_step
import pobax.env as E
from pobax.env import make
from pobax.eval import EvalError, RunLoadError, evaluate, format_ci, format_eval, load_run, plot_runs, train
from pobax.eval._files import json_digest
from pobax.eval._seal import without_seal
from pobax.eval._listing import list_runs
from pobax.eval._report import read_rows
from pobax.eval._given_env import env_digest, given_env_mismatch, given_env_record

import pobax.eval._plots
from _envs import ConstantReward
from _hostile import CFG, as_a_notebook, copy, write_summary  # noqa: F401  (the fixture)

def _tiny(**kw):
    return dataclasses.replace(CFG, **{**dict(env="tmaze_1", num_envs=4, num_steps=16, num_minibatches=2,
                                              update_epochs=1, total_steps=256, num_seeds=1, num_chunks=1), **kw})


pytestmark = pytest.mark.usefixtures("as_a_notebook")


@pytest.mark.parametrize("env_id", ["tmaze_10", "battleship_10"])
@pytest.mark.parametrize("action", [0.5, 2.9, "0", True, [1], np.float32(1), jnp.float32(1), jnp.array([1])])
def test_a_discrete_action_of_another_kind_is_refused_not_read_as_another(env_id, action):
    env = make(env_id)
    state, _ = env.reset(key=jax.random.key(0))
    with pytest.raises(ValueError, match=r"actions are integer scalars \(shape \(\)\)"):
        env.step(state, action, key=jax.random.key(1))
    for ok in (1, np.int64(1), np.uint8(1), jnp.int32(1)):  # integers of any width are actions
        env.step(state, ok, key=jax.random.key(1))
    with pytest.raises(ValueError, match="integer scalars"):  # the previous action's one-hot would disagree
        concat = make(env_id, action_concat=True)
        concat.step(concat.reset(key=jax.random.key(0))[0], 1.7, key=jax.random.key(1))


def test_boolean_options_and_ids_of_the_wrong_type_are_refused():
    for kw in ({"wrappers": "no"}, {"action_concat": "no"}, {"action_concat": 1}):
        with pytest.raises(ValueError, match="must be True or False"):
            make("tmaze_10", **kw)
    with pytest.raises(ValueError, match="the environment ID is a string"):
        make(10)
    assert make("tmaze_10", time_limit=jnp.int32(5)).max_steps_in_episode == 5  # a JAX count is a count


def test_a_finished_runs_edited_config_json_is_refused_by_every_reader(tmp_path, finished):
    run = copy(finished, tmp_path / "run")
    original = (run / "config.json").read_text()
    record = json.loads(original)
    (run / "config.json").write_text(json.dumps(record))  # another layout, the same configuration: still the run's
    assert load_run(run).config.env == "tmaze_5"
    for edit in ({"env": "tmaze_3"}, {"lr": [float("nan")]}, {"hidden_size": 16}):
        record = json.loads(original)
        record["config"].update(edit)
        (run / "config.json").write_text(json.dumps(record))
        with pytest.raises(RunLoadError, match="config.json' differs from the configuration its run finished with"):
            load_run(run)
        with pytest.raises(RunLoadError, match="config.json' differs"):
            evaluate(run, episodes=2, save=False)
        assert [r["state"] for r in list_runs(tmp_path)] == ["damaged"]


def test_a_summary_sealed_without_its_config_is_checked_against_it(tmp_path, finished):
    """Summaries sealed before the seal held config.json: what the summary shows of the configuration must match."""
    run = copy(finished, tmp_path / "run")
    summary = json.loads((run / "summary.json").read_text())
    del summary["sha256"]["config.json"]
    summary["sha256"]["summary.json"] = json_digest(without_seal(summary))
    (run / "summary.json").write_text(json.dumps(summary))
    original = (run / "config.json").read_text()
    assert load_run(run).config.env == "tmaze_5"
    for edit, what in (({"env": "tmaze_3"}, "env differs"), ({"lr": [1e-3]}, "set 0's lr differs")):
        record = json.loads(original)
        record["config"].update(edit)
        (run / "config.json").write_text(json.dumps(record))
        with pytest.raises(RunLoadError, match=f"does not match the run's finished summary.json \\({what}"):
            load_run(run)


def test_evaluate_refuses_a_greedy_that_is_not_a_bool(finished):
    with pytest.raises(EvalError, match="greedy must be True or False, got 'no'"):
        evaluate(finished, episodes=2, greedy="no", save=False)


@pytest.mark.slow
def test_an_environment_given_to_train_must_reset_and_is_needed_to_read_the_run_back(tmp_path, monkeypatch):
    cfg = _tiny()
    with pytest.raises(ConfigError, match="does not reset its episodes"):
        train(cfg, save=False, progress=False, env=make("tmaze_1", wrappers=False))
    with pytest.raises(ConfigError, match="env must be a pobax environment"):
        train(cfg, save=False, progress=False, env="tmaze_1")
    env = make("tmaze_1")
    train(cfg, tmp_path / "given", progress=False, env=env)
    assert json.loads((tmp_path / "given" / "config.json").read_text())["env_given"] == "AutoReset(TMaze)"
    with pytest.raises(RunLoadError, match=r"trained in an environment given to train\(env=...\)"):
        load_run(tmp_path / "given")
    assert load_run(tmp_path / "given", env=env).finished
    with pytest.raises(RunLoadError, match=r"trained in AutoReset\(TMaze\) with parameters other than those"):
        load_run(tmp_path / "given", env=make("tmaze_2"))  # the same classes, a longer corridor
    with pytest.raises(EvalError, match=r"another observability \('full'\) would play tmaze_1's registered one"):
        evaluate(load_run(tmp_path / "given", env=env), episodes=2, observability="full", save=False)
    played = evaluate(load_run(tmp_path / "given", env=env), episodes=2, observability="partial")
    assert len(played.episodes) == 2  # its own observability named: played in the environment it trained in
    # and named by it, not by the ID its configuration kept
    assert [p.name for p in played.files] == ["eval-given-stochastic-seed0.json", "eval-given-stochastic-seed0.csv"]
    assert (played.summary["env"], played.summary["trained_observability"]) == ("AutoReset(TMaze)", "given")
    assert format_eval(played).startswith("AutoReset(TMaze) gru (trained on given) on given: ")
    train(cfg, tmp_path / "registered", progress=False)
    with pytest.raises(RunLoadError, match="trained in its registered environment"):
        load_run(tmp_path / "registered", env=env)
    # `pobax results` and the figures name the environment each trained in, not the ID its configuration kept, and
    # draw none of that ID's reference returns over a given environment's curve
    assert [(r["env"], r["observability"]) for r in list_runs(tmp_path)] == [("AutoReset(TMaze)", "given"),
                                                                               ("tmaze_1", "partial")]
    plot_runs([tmp_path / "given", tmp_path / "registered"], tmp_path / "f.png", data=tmp_path / "f.json")
    labels = list(json.loads((tmp_path / "f.json").read_text())["curves"])
    assert [x.split(" gru")[0] for x in labels] == ["AutoReset(TMaze) given", "tmaze_1 partial"]
    drawn = []  # the reference lines each figure draws
    draw = pobax.eval._plots._draw_bands
    monkeypatch.setattr(pobax.eval._plots, "_draw_bands", lambda *a, **k: drawn.append(k["hlines"]) or draw(*a, **k))
    assert json.loads((tmp_path / "given" / "config.json").read_text())["env_spec"]["reference"] == {}
    for run in ("registered", "given"):
        plot_runs(tmp_path / run, tmp_path / f"{run}.png")
    # a given environment's run written before its config.json left cfg.env's reference out: none drawn either
    config = json.loads((tmp_path / "given" / "config.json").read_text())
    config["env_spec"] = json.loads((tmp_path / "registered" / "config.json").read_text())["env_spec"]
    (tmp_path / "given" / "config.json").write_text(json.dumps(config))
    write_summary(tmp_path / "given", without_seal(json.loads((tmp_path / "given" / "summary.json").read_text())))
    plot_runs(tmp_path / "given", tmp_path / "legacy.png")
    assert drawn[0] and all(k.startswith("tmaze_1: ") for k in drawn[0]) and drawn[1:] == [{}, {}]


@pytest.mark.slow
def test_a_resume_without_the_environment_the_run_trained_in_is_refused(tmp_path):
    cfg = _tiny(num_chunks=2)
    env = make("tmaze_1")
    train(cfg, tmp_path / "r", progress=False, env=env, max_chunks=1)
    with pytest.raises(Exception, match=r"resume it from Python with"):
        train(cfg, tmp_path / "r", progress=False, resume=True)
    with pytest.raises(Exception, match=r"with parameters other than those of the one given now: resume it"):
        train(cfg, tmp_path / "r", progress=False, resume=True, env=make("tmaze_2"))
    assert train(cfg, tmp_path / "r", progress=False, resume=True, env=env).summary["sets"]


def test_a_given_environment_is_told_apart_by_its_classes_and_its_parameters():
    record = {"config": {"env": "tmaze_5"}, **given_env_record(make("tmaze_1"))}
    assert given_env_mismatch(record, make("tmaze_1")) is None  # another instance, the same environment
    assert "with parameters other than" in given_env_mismatch(record, make("tmaze_2"))
    assert "not in the AutoReset(Battleship) given now" in given_env_mismatch(record, make("battleship_10"))
    assert "registered one" in given_env_mismatch(record, None)
    legacy = {k: v for k, v in record.items() if k != "env_given_digest"}  # written before the digest was kept
    assert given_env_mismatch(legacy, make("tmaze_2")) is None
    assert env_digest(make("rocksample_11_11")) != env_digest(make("rocksample_11_11", map_seed=1))  # its rock array
    # the digest a resume compares is the same in another process (nothing in it is an address)
    code = ("from pobax.env import make; from pobax.eval._given_env import env_digest; "
            "print(env_digest(make('tmaze_1')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert out.stdout.strip() == record["env_given_digest"]


def test_readers_of_a_root_that_does_not_exist_say_so(tmp_path):
    for read in (list_runs, read_rows):
        with pytest.raises(FileNotFoundError, match="it does not exist"):
            read(tmp_path / "no-such-dir")


def test_gae_refuses_inputs_that_would_broadcast_or_flip_signs():
    T = 4
    v = jnp.ones(T)
    f = jnp.zeros(T, bool)
    with pytest.raises(ValueError, match="every input has one shape"):
        gae(jnp.zeros((T, 1)), v, v, f, f, 0.99, 0.95)
    with pytest.raises(ValueError, match="terminated and truncated are boolean arrays, got int32"):
        gae(jnp.zeros(T), v, v, jnp.array([0, 0, 2, 0]), f, 0.99, 0.95)
    with pytest.raises(ValueError, match="method must be one of"):
        gae(jnp.zeros(T), v, v, f, f, 0.99, 0.95, method="weight")
    with pytest.raises(ValueError, match="gamma must be in"):
        gae(jnp.zeros(T), v, v, f, f, 1.5, 0.95)
    lists, _ = gae([0.0] * T, [1.0] * T, [1.0] * T, [False] * T, [False] * T, 0.9, 0.9)  # lists are arrays
    np.testing.assert_allclose(lists, gae(jnp.zeros(T), v, v, f, f, 0.9, 0.9)[0])


def test_policy_step_takes_a_python_bool_and_names_a_stacked_model(finished):
    run = load_run(finished)
    model = run.pick(set=0, seed=0)
    _, ts = run.env.reset(key=jax.random.key(0))
    _, action, _, _ = policy_step(model, model.init_carry(), ts.obs, True, jax.random.key(1))
    assert action.shape == ()
    with pytest.raises(ValueError, match=r"pass one run's model \(LoadedRun.pick"):
        policy_step(run.model, model.init_carry(), ts.obs, True, jax.random.key(1))
    with pytest.raises(ValueError, match="start is one flag"):
        policy_step(model, model.init_carry(), ts.obs, jnp.array([True]), jax.random.key(1))


@pytest.mark.parametrize("args, kw, message", [
    ((dataclasses.asdict(CFG),), {}, "train needs a TrainConfig, got a dict"),  # was an AttributeError
    ((CFG, 5), {}, "train: out must be a directory path (a str or Path, or None), got 5"),  # was pathlib's TypeError
    ((CFG, "a\x00b"), {}, "holds a NUL character"),  # was os's bare "embedded null byte"
    ((CFG,), {"save": "no"}, "save must be True or False, got 'no'"),  # was a saved run
    ((CFG,), {"progress": None}, "progress must be True or False, got None")])
def test_train_refuses_arguments_of_the_wrong_kind(tmp_path, monkeypatch, args, kw, message):
    monkeypatch.chdir(tmp_path)  # where a default run directory would go
    with pytest.raises(ConfigError) as e:
        train(*args, **kw)
    assert message in str(e.value) and "\n" not in str(e.value)
    assert list(tmp_path.iterdir()) == []


def test_returns_past_float32_are_told_and_summarised_as_infinite(tmp_path, capsys):
    """An environment whose returns pass float32's range (1e37 a step for 40 steps: 4e38), trained on scaled rewards: it trained (nothing diverged)
    but its undiscounted return read nan [nan, nan], as if no episode had ended, with no word of why."""
    r = train(_tiny(reward_scale=1e-37, total_steps=512), tmp_path / "r", env=E.AutoReset(ConstantReward(reward=1e37, discount=0.5, length=40)),
              progress=False)
    assert "passed float32's largest value" in capsys.readouterr().err
    s = r.summary["sets"][0]
    assert s["diverged"] == 0 and s["return"]["mean"] == np.inf and format_ci(s["return"]) == "inf [nan, nan]"
    assert format_ci(s["disc_return"]).startswith("2e+37")


def test_runs_chunks_refuses_a_state_an_earlier_call_consumed():
    from pobax.agent import Runs

    runs = Runs(CFG)
    state = runs.init()
    last = [c.state for c in runs.chunks(state, 0, 1)][-1]
    with pytest.raises(ValueError, match=r"^Runs.chunks: this state was consumed by an earlier call .*chunk.state"):
        next(runs.chunks(state, 1, 2))
    assert [c.index for c in runs.chunks(last, 1, 2)] == [1]  # the state the last chunk yielded continues


def test_a_checkpoints_evaluation_does_not_block_the_finished_models(tmp_path, stopped):
    run = copy(stopped, tmp_path / "r")
    early = evaluate(run, episodes=2)
    assert [f.name for f in early.files] == ["eval-partial-stochastic-seed0-chunk3.json",
                                             "eval-partial-stochastic-seed0-chunk3.csv"]
    kept = {f: f.read_bytes() for f in early.files}
    train(CFG, run, progress=False, resume=True)
    late = evaluate(run, episodes=2)
    assert [f.name for f in late.files] == ["eval-partial-stochastic-seed0.json", "eval-partial-stochastic-seed0.csv"]
    assert late.summary["model"] == "model.eqx" and early.summary["model"] == "checkpoint after chunk 3"
    assert {f: f.read_bytes() for f in early.files} == kept


@pytest.mark.parametrize("key", [0, None, "0"])
def test_a_key_that_is_not_a_jax_key_is_named_in_one_line(key):
    env = E.make("tmaze_5")  # TimeLimit inside AutoReset: the outermost names it first
    with pytest.raises(TypeError, match=r"^reset: key must be a JAX random key, e\.g\. jax\.random\.key\(0\), got "):
        env.reset(key=key)
    state, _ = env.reset(key=jax.random.key(0))
    with pytest.raises(TypeError, match=r"^step: key must be a JAX random key"):
        env.step(state, jnp.asarray(0), key=key)
    env.reset(key=jax.random.PRNGKey(0))  # raw key data still accepted
