"""Looking at what was learned: `load_run`, `evaluate`, `render_episode`, their commands and the package surface."""

import dataclasses
import json
import re
import shutil
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest
from PIL import Image

import cli
import pobax
from pobax.agent import TrainConfig
from pobax.eval import EvalError, LoadedRun, RunDir, RunLoadError, evaluate, load_run, plot_runs, render_episode

# 2 hyperparameter sets × 2 seeds, 4 updates in 2 chunks, with observation statistics to save and load.
TINY = TrainConfig(env="tmaze_3", memory="gru", hidden_size=8, num_envs=2, num_minibatches=2, num_steps=16,
                   total_steps=128, num_seeds=2, num_chunks=2, lr=(1e-3, 1e-4), normalize_obs=True, fast_compile=True)
SMALL = dict(hidden_size=8, num_envs=2, num_minibatches=1, num_steps=8, total_steps=16, num_seeds=1, fast_compile=True)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    path = tmp_path_factory.mktemp("runs") / "tmaze"
    return path, pobax.train(TINY, path, progress=False)


def _leaves_equal(a, b) -> bool:
    la, lb = jax.tree.leaves(eqx.filter(a, eqx.is_array)), jax.tree.leaves(eqx.filter(b, eqx.is_array))
    return len(la) == len(lb) and all(np.array_equal(x, y) for x, y in zip(la, lb))


def test_load_run_round_trip(trained):
    path, result = trained
    run = pobax.load_run(path)
    assert pobax.load_run is pobax.eval.load_run
    assert run.config == TINY and run.finished and run.source == "model.eqx" and run.num_runs == 4
    assert _leaves_equal(run.model, result.state.model)
    assert _leaves_equal(run.obs_norm, result.state.obs_norm)  # obs_norm.eqx: the statistics the runs acted on
    assert list(run.hp_index) == [0, 0, 1, 1] and list(run.seed_index) == [0, 1, 0, 1]
    assert _leaves_equal(run.pick(set=1, seed=1), jax.tree.map(lambda x: x[3], result.state.model))
    assert _leaves_equal(run.pick(index=2), jax.tree.map(lambda x: x[2], result.state.model))
    assert _leaves_equal(run.pick_obs_norm(index=2), jax.tree.map(lambda x: x[2], result.state.obs_norm))
    pd.testing.assert_frame_equal(run.metrics, pd.read_csv(path / "metrics.csv"))
    assert run.summary["best_by_auc"] == result.summary["best_by_auc"] == run.best_set
    assert run.env.observation_space.shape == (4,)
    # RunDir.load_model without a template says where to get one (it used to return None)
    with pytest.raises(TypeError, match="pobax.load_run"):
        RunDir(path).load_model()
    with pytest.raises(RunLoadError, match="set 2 does not exist"):
        run.pick(set=2)
    with pytest.raises(RunLoadError, match="Seed index 5"):
        run.pick(set=0, seed=5)
    for i in (4, -1):  # not another run's statistics (JAX clamps an index out of range)
        with pytest.raises(RunLoadError, match="Run index"):
            run.pick_obs_norm(index=i)


@pytest.mark.slow
def test_load_run_of_an_interrupted_run_reads_its_checkpoint(tmp_path):
    cfg = dataclasses.replace(TINY, lr=(1e-3,), normalize_obs=False)
    result = pobax.train(cfg, tmp_path / "r", progress=False, max_chunks=1)
    # a run stopped after writing the metrics of its next chunk, before checkpointing it (a resume trains it again):
    # the metrics and summary are those of the checkpointed state, not of the chunk it has not trained
    later = pd.read_csv(tmp_path / "r" / "metrics" / "00000.csv")
    later = later.assign(update=later["update"] + 2, disc_return=9.0)
    later.to_csv(tmp_path / "r" / "metrics" / "00001.csv", index=False)
    run = load_run(tmp_path / "r")
    assert not run.finished and run.source == "checkpoint after chunk 1"
    assert _leaves_equal(run.model, result.state.model)
    assert len(run.metrics) == 2 * 2 and run.summary["sets"]  # two updates of two seeds so far
    pd.testing.assert_frame_equal(run.metrics, result.metrics)


def test_load_run_errors_are_one_line_value_errors(tmp_path):
    (tmp_path / "file").write_text("x")
    (tmp_path / "empty").mkdir()
    started = tmp_path / "started"  # a run stopped before its first checkpoint: config.json only
    started.mkdir()
    (started / "config.json").write_text(json.dumps({"config": dataclasses.asdict(TINY)}))
    for where, message in [(tmp_path / "missing", "does not exist"), (tmp_path / "file", "not a run directory"),
                           (tmp_path / "empty", "not a run directory"), (started, "no trained model yet")]:
        with pytest.raises(RunLoadError, match=message) as e:
            load_run(where)
        assert isinstance(e.value, ValueError) and "\n" not in str(e.value)


def test_a_folder_of_runs_given_as_a_run_names_the_runs_below_it(trained, tmp_path):
    path, _ = trained
    folder = tmp_path / "bench"  # as a benchmark's --out: runs/ENV/NAME/
    shutil.copytree(path, folder / "runs" / "tmaze_3" / "gru")
    for call in (lambda: load_run(folder), lambda: plot_runs(folder, tmp_path / "curves.png")):
        with pytest.raises((RunLoadError, FileNotFoundError)) as e:
            call()
        message = str(e.value)
        assert "it holds 1 run directory below it" in message and "\n" not in message, message
        assert repr(str(folder / "runs" / "tmaze_3" / "gru")) in message and f"--root {folder}`" in message


def test_evaluate_is_deterministic_and_measures_every_run(trained, tmp_path):
    path, _ = trained
    run = load_run(path)
    a = evaluate(run, episodes=6, seed=3, out=tmp_path)
    b = evaluate(path, episodes=6, seed=3, save=False)
    c = evaluate(run, episodes=6, seed=4, save=False)
    pd.testing.assert_frame_equal(a.episodes, b.episodes)
    assert not a.episodes.equals(c.episodes)
    df = a.episodes
    assert len(df) == 4 * 6
    assert {"hp_index", "seed", "episode", "return", "disc_return", "length", "terminated", "truncated",
            "cut"} <= set(df.columns)
    assert sorted(set(zip(df.hp_index, df.seed))) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    ended = df[df.terminated]  # T-Maze pays once, on the last step: the discounted return is γ^(length-1) of it
    assert np.allclose(ended.disc_return, ended["return"] * 0.99 ** (ended.length - 1), atol=1e-5)
    # each episode ended in exactly one way: terminated, truncated by the time limit, or cut by max_steps
    assert (df.length >= 1).all() and (df.terminated.astype(int) + df.truncated + df.cut == 1).all()
    assert [f.name for f in a.files] == ["eval-partial-stochastic-seed3.json", "eval-partial-stochastic-seed3.csv"]
    summary = json.loads(a.files[0].read_text())
    assert len(summary["sets"]) == 2 and len(summary["runs"]) == 4
    for s in summary["sets"]:
        assert s["disc_return"]["ci_low"] <= s["disc_return"]["mean"] <= s["disc_return"]["ci_high"]
        per_seed = df[df.hp_index == s["hp_index"]].groupby("seed")["return"].mean()
        assert np.allclose(s["return"]["per_seed"], per_seed)
    pd.testing.assert_frame_equal(pd.read_csv(a.files[1]), df, check_dtype=False)
    short = evaluate(run, episodes=6, max_steps=5, save=False).episodes
    assert (short.length <= 5).all() and short.cut.any()
    assert list(short.cut) == list((short.length == 5) & ~short.terminated & ~short.truncated)


def test_seeds_that_diverged_in_training_are_counted_not_averaged(trained):
    path, _ = trained
    run = load_run(path)
    m = run.metrics.copy()
    m.loc[(m.hp_index == 0) & (m.seed == 1) & (m["update"] == 2), "nonfinite"] = 1  # as a NaN loss would mark it
    result = evaluate(dataclasses.replace(run, metrics=m), episodes=4, seed=1, save=False)
    s0, s1 = result.summary["sets"]
    assert (s0["diverged"], s0["diverged_seeds"], s0["num_seeds"]) == (1, [1], 2) and s1["diverged"] == 0
    df = result.episodes
    assert np.allclose(s0["return"]["per_seed"], [df[(df.hp_index == 0) & (df.seed == 0)]["return"].mean()])
    assert len(s1["return"]["per_seed"]) == 2 and len(result.summary["runs"]) == 4  # the run itself is still listed
    assert "1 of 2 seeds diverged" in pobax.eval.format_eval(result)


def test_the_policy_steps_as_the_network_replays(trained):
    """One step at a time from the carry the rollout would use, the memory reset at the episode's start: the values
    and memory states of a played episode are the network's on the whole sequence (as PPO's replay computes)."""
    path, _ = trained
    run = load_run(path)
    from pobax.eval._episodes import record_episode

    ep = record_episode(run, lambda env, state, obs: {"obs": obs}, index=3, seed=1, max_steps=30)
    model, norm = run.pick(index=3), run.pick_obs_norm(index=3)
    obs = norm(jnp.asarray(ep.views["obs"][:-1]))
    starts = jnp.zeros((ep.length,), bool).at[0].set(True)
    junk = jax.tree.map(lambda x: x + 1.0, model.init_carry())  # whatever came before: reset by the start flag
    _, _, values = model(junk, obs, starts)
    assert np.allclose(values, ep.values, atol=1e-5)
    _, hidden = model.memory(junk, jax.vmap(model.encoder)(obs), starts)
    assert np.allclose(hidden, ep.memory, atol=1e-5)


@pytest.mark.parametrize("greedy", [False, True])
def test_evaluate_plays_the_episode_record_episode_plays(trained, greedy):
    """`evaluate`'s batched episodes and `record_episode`'s step-by-step one are the same episode (the latter checked
    against the network's replay above): same policy inputs, memory resets, keys and discounting."""
    path, _ = trained
    run = load_run(path)
    from pobax.eval._episodes import record_episode

    df = evaluate(run, episodes=2, seed=1, greedy=greedy, save=False).episodes
    for i in (0, 3):
        ep = record_episode(run, lambda env, state, obs: {}, index=i, seed=1, greedy=greedy, max_steps=10_000)
        row = df[(df.hp_index == run.hp_index[i]) & (df.seed == run.seed_index[i]) & (df.episode == 0)].iloc[0]
        assert (row.length, row.terminated, row.truncated) == (ep.length, ep.terminated, ep.truncated)
        assert np.allclose([row["return"], row.disc_return], ep.returns, atol=1e-5)


def test_an_episode_played_in_blocks_is_the_episode_played_at_once(trained, monkeypatch):
    """record_episode plays `RECORD_BLOCK` steps a program call (its work follows the episode, not --steps): blocks of
    3 steps, ending mid-block and cut by max_steps mid-block, give the episode one call gives."""
    from pobax.eval import _episodes

    run = load_run(trained[0])
    capture = lambda env, state, obs: {"obs": obs}  # noqa: E731
    for max_steps in (10_000, 7):
        whole = _episodes.record_episode(run, capture, index=3, seed=1, max_steps=max_steps)
        with monkeypatch.context() as m:
            m.setattr(_episodes, "RECORD_BLOCK", 3)
            blocks = _episodes.record_episode(run, capture, index=3, seed=1, max_steps=max_steps)
        assert whole.length == blocks.length > 3  # (past the first block of 3)
        if max_steps == 7:
            assert whole.length == 7 and not whole.terminated  # cut by max_steps in the third block
        assert (whole.terminated, whole.truncated) == (blocks.terminated, blocks.truncated)
        for a, b in ((whole.actions, blocks.actions), (whole.rewards, blocks.rewards), (whole.values, blocks.values),
                     (whole.views["obs"], blocks.views["obs"])):
            np.testing.assert_allclose(a, b, atol=1e-6)


def test_a_run_without_its_observation_statistics_is_refused(trained):
    path, _ = trained
    run = dataclasses.replace(load_run(path), obs_norm=None)  # as a run finished before obs_norm.eqx existed
    for call in (lambda: evaluate(run, save=False), lambda: render_episode(run, None)):
        with pytest.raises(EvalError, match="statistics were not saved"):
            call()


@pytest.mark.slow
def test_memory_trace_of_every_memory():
    """Every built-in memory's state shows in the picture as a real vector (LRU and FFM carry (re, im) pairs), and a
    complex carry (a user's cell may have one) as its real then imaginary parts."""
    from pobax.agent._ppo import make_model
    from pobax.eval._episodes import memory_trace
    from pobax.memory import MEMORIES

    env = pobax.env.make("tmaze_3")
    for name in MEMORIES:
        model = make_model(TrainConfig(env="tmaze_3", memory=name, hidden_size=8), env, jax.random.key(0))
        carry = jax.tree.map(lambda x: x + 1 if jnp.issubdtype(x.dtype, jnp.inexact) else x, model.init_carry())
        trace = memory_trace(carry)
        if name == "memoryless":
            assert trace is None
            continue
        assert trace.ndim == 1 and trace.dtype == jnp.float32 and trace.size >= 8 and (trace != 0).any(), name
    trxl = make_model(TrainConfig(env="tmaze_3", memory="trxl", hidden_size=8), env, jax.random.key(0)).init_carry()
    cache = jnp.arange(trxl.memory.size, dtype=jnp.float32).reshape(trxl.memory.shape)
    trxl = eqx.tree_at(lambda c: c.memory, trxl, cache)
    assert np.array_equal(memory_trace(trxl), trxl.memory[-1, -1])  # the newest cached input of the last layer
    complex_carry = (jnp.array([[1 + 2j, 3 - 4j]], jnp.complex64), jnp.array(7, jnp.int32))
    assert np.array_equal(memory_trace(complex_carry), np.array([1, 3, 2, -4], np.float32))


@pytest.mark.slow
def test_another_observability(trained, tmp_path):
    path, _ = trained
    full = evaluate(path, episodes=2, observability="full", save=False)
    assert full.summary["observability"] == "full" and full.summary["trained_observability"] == "partial"
    ship = LoadedRun.untrained(TrainConfig(env="battleship_6", **SMALL))
    with pytest.raises(EvalError, match=r"shape \(72,\).*trained on 'partial' observations of shape \(37,\)"):
        evaluate(ship, observability="perfect_memory")


def test_eval_and_render_commands(trained, tmp_path, capsys):
    path, _ = trained
    cli.main(["eval", str(path), "--episodes", "3", "--out", str(tmp_path / "e")])
    printed = capsys.readouterr().out
    assert "set 0" in printed and "set 1" in printed and "discounted" in printed
    assert "per run, over its episodes" in printed and len(re.findall(r"set \d seed \d:", printed)) == 4
    assert (tmp_path / "e" / "eval-partial-stochastic-seed0.csv").exists()
    cli.main(["render", str(path), "--out", str(tmp_path / "ep.gif"), "--set", "1", "--run-seed", "1"])
    printed = capsys.readouterr().out
    frames = int(printed.split()[0])
    assert Image.open(tmp_path / "ep.gif").n_frames == frames and (tmp_path / "ep.png").exists()
    for argv, message in [(["eval", str(tmp_path / "nope")], "does not exist"),
                          (["render", str(path), "--out", str(tmp_path / "x.mp4")], "name a .gif"),
                          (["render", str(path), "--env", "tmaze_5"], "not both"),
                          (["eval", str(path), "--observability", "perfect_memory"], "no observability")]:
        with pytest.raises(SystemExit) as e:
            cli.main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and message in err and err.strip().count("\n") == 0


def _check_animation(result, gif, memory: bool):
    """The GIF has one frame per state of the episode (its steps + 1), no frame is blank, the picture changes."""
    n = result.episode.length + 1
    assert len(result.frames) == n and Image.open(gif).n_frames == n and Image.open(gif.with_suffix(".png")).size
    for f in result.frames:
        assert f.ndim == 3 and f.std() > 10 and (f < 200).mean() > 0.01
    assert any(not np.array_equal(a, b) for a, b in zip(result.frames, result.frames[1:]))
    assert (result.episode.memory is not None) == memory


def test_render_tmaze_shows_the_corridor_the_cue_and_the_agent(trained, tmp_path):
    path, _ = trained
    r = render_episode(path, tmp_path / "t.gif", set=0, seed_index=1, seed=2, max_steps=12)
    _check_animation(r, tmp_path / "t.gif", memory=True)
    assert r.episode.memory.shape == (r.episode.length, 8)  # the GRU's hidden state after each step
    assert set(r.episode.views) == {"pos", "goal_up"} and r.episode.views["pos"][0] == 0


@pytest.mark.parametrize("env, memory, steps", [("rocksample_5_3", "gru", 25), ("battleship_6", "memoryless", 15),
                                                pytest.param("Navix-DMLab-Maze-01-v0", "gru", 10,
                                                             marks=pytest.mark.slow)])
def test_render_grid_worlds(tmp_path, env, memory, steps):
    run = LoadedRun.untrained(TrainConfig(env=env, memory=memory, **SMALL))
    r = render_episode(run, tmp_path / "x.gif", max_steps=steps)
    _check_animation(r, tmp_path / "x.gif", memory=memory != "memoryless")
    assert r.episode.length <= steps


def test_maze_pictures_outline_the_cells_the_agent_sees():
    """The maze drawer outlines the 2x3 cells ahead where the observation holds them (partial, perfect_memory), not on
    the full map."""
    from pobax.env import DMLabMaze
    from pobax.eval._render import CUE, _maze_draw

    outlined = {}
    for obs in ("partial", "perfect_memory", "full"):
        env = DMLabMaze("01", obs)
        state, _ = env.reset(key=jax.random.key(0))
        views = {k: np.asarray(getattr(state, k))[None] for k in ("position", "direction", "goal")}
        frame = np.asarray(_maze_draw(env, views, np.array([2]))[0])
        outlined[obs] = int(np.all(frame == np.asarray(CUE), axis=-1).sum())
    assert outlined["partial"] == outlined["perfect_memory"] > 0 == outlined["full"]


def test_heavy_family_pictures_from_captured_views():
    """The drawers of masked MuJoCo (joint trajectories) and pixel environments (their frames) on made-up views
    (the episodes themselves are rendered in the slow tests below)."""
    from pobax.eval._render import drawer_for

    env = pobax.env.make("Walker-V-v0")
    t = np.arange(9, dtype=np.float32)
    views = {"pos": np.sin(t[:, None] / 3 + np.arange(8)), "x": t / 10}
    frames = drawer_for(env).draw(env.unwrapped, views, np.zeros((8, 6), np.float32))
    assert len(frames) == 9 and all(f.std() > 10 for f in frames) and not np.array_equal(frames[0], frames[-1])
    from pobax.eval._render import _pixels_draw

    pixels = np.random.default_rng(0).integers(0, 255, (5, 27, 33, 3), dtype=np.uint8)
    frames = _pixels_draw(None, {"frame": pixels}, np.zeros(4, np.int32))
    k = frames[0].shape[0] // 27  # each pixel drawn k × k
    assert len(frames) == 5 and k >= 5 and np.array_equal(frames[0][::k, ::k], pixels[0])


@pytest.mark.slow
@pytest.mark.parametrize("env", ["Walker-V-v0", "halfcheetah_pixels", "craftax_pixels"])
def test_render_heavy_families(tmp_path, env):
    run = LoadedRun.untrained(TrainConfig(env=env, **SMALL))
    r = render_episode(run, tmp_path / "x.gif", max_steps=6)
    _check_animation(r, tmp_path / "x.gif", memory=True)


def test_package_surface_in_a_fresh_interpreter():
    code = ("import pobax; print(pobax.__version__, pobax.env.make('tmaze_5').gamma, pobax.memory.GRU.__name__, "
            "pobax.agent.TrainConfig.__name__, pobax.eval.evaluate.__name__, pobax.load_run.__name__, "
            "pobax.evaluate.__name__, pobax.render_episode.__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={"JAX_PLATFORMS": "cpu"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[1:] == ["0.99", "GRU", "TrainConfig", "evaluate", "load_run", "evaluate", "render_episode"]
    from pobax.eval import _animation, _evaluate, _load, _render

    for module in (_load, _evaluate, _render, _animation):
        public = [v for k, v in vars(module).items() if not k.startswith("_") and callable(v)
                  and getattr(v, "__module__", None) == module.__name__]
        assert public and all(v.__doc__ for v in public), module.__name__
    methods = [LoadedRun.pick, LoadedRun.index, LoadedRun.untrained, LoadedRun.pick_obs_norm]
    assert all(m.__doc__ for m in methods)


def test_plot_runs_takes_a_path_or_a_list(trained, tmp_path):
    path, _ = trained
    assert pobax.eval.plot_runs(path, tmp_path / "one.png").stat().st_size > 1000
    assert pobax.eval.plot_runs([str(path)], tmp_path / "list.png").stat().st_size > 1000


def test_plot_of_a_training_metric_writes_its_curves(trained, tmp_path, capsys):
    path, _ = trained
    data = tmp_path / "entropy.json"
    pobax.eval.plot_runs(path, tmp_path / "e.png", column="entropy", data=data)
    (label, curve), = json.loads(data.read_text())["curves"].items()
    metrics = RunDir(path).metrics()
    first = metrics[metrics.hp_index == 0].sort_values(["seed", "env_step"])
    # 4 updates, one bin each: a seed's binned entropy is its update's, the mean is over seeds
    assert curve["env_step"] == sorted(first.env_step.unique().tolist())
    for seed, g in first.groupby("seed"):
        assert curve["per_seed"][str(seed)] == pytest.approx(g.entropy.tolist(), rel=1e-5)
    assert curve["mean"] == pytest.approx(first.groupby("env_step").entropy.mean().tolist(), rel=1e-5)
    assert "gru" in label and curve["run_dir"] == str(path)
    with pytest.raises(ValueError, match="logs no metric 'entropi'; its metrics are: .*entropy"):
        pobax.eval.plot_runs(path, tmp_path / "x.png", column="entropi")
    # from the command line; --metric and --undiscounted together are refused
    cli.main(["plot", str(path), "--metric", "ep_length", "--out", str(tmp_path / "l.png"), "--json",
              str(tmp_path / "l.json")])
    assert "curves: " in capsys.readouterr().out and json.loads((tmp_path / "l.json").read_text())["column"] == \
        "ep_length"
    with pytest.raises(SystemExit) as e:
        cli.main(["plot", str(path), "--metric", "entropy", "--undiscounted", "--out", str(tmp_path / "u.png")])
    assert e.value.code == 2 and "give one of them" in capsys.readouterr().err


def test_evaluation_intervals_follow_the_number_of_values_as_training_summaries_do():
    """eval's intervals were percentile bootstraps at any count: over 2 episodes, [min, max], read as a 95% CI.
    Below 10 values they are Student's t, as every other table's (`mean_ci`)."""
    from pobax.eval._evaluate import _stat

    two = _stat([1.0, 3.0])
    assert two["mean"] == 2.0 and two["ci_low"] < 1.0 and two["ci_high"] > 3.0  # t(1 df): 2 ± 12.7
    many = _stat(np.arange(12.0))
    assert 0.0 < many["ci_low"] < many["mean"] < many["ci_high"] < 11.0  # a bootstrap, within the values
