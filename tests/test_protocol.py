"""The paper's protocol (`benchmark --protocol paper`), intervals by seed count, and the commit a record states."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pobax.agent import validate
from pobax.env import PAPER_GRID, PAPER_LD_GRID, SUITES, spec
from pobax.eval import mean_ci, run_benchmark, student_t_ci
from pobax.eval._gap import gap_verdict
from pobax.eval._plan import BenchmarkError, resolve_envs
from pobax.eval._protocol import (EXTRA_CEILING, ProtocolError, evaluation_config, evaluation_keys, protocol_agents,
                                  protocol_config, select, selection_keys)

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("env", ["tmaze_10", "rocksample_11_11", "battleship_10", "Navix-DMLab-Maze-01-v0"])
def test_selection_and_evaluation_seeds_are_disjoint(env):
    for agent in protocol_agents(env, ("floor", "gru", "ld", "trxl", "ceiling")):
        sweep, n_eval = protocol_config(env, agent, "paper")
        assert sweep.num_seeds == spec(env).protocol()["selection_seeds"] and n_eval == 30
        grid = spec(env).protocol()["ld_grid" if agent.double_critic else "grid"]
        assert {k: tuple(getattr(sweep, k)) for k in grid} == {k: tuple(v) for k, v in grid.items()}
        ecfg = evaluation_config(sweep, {k: v[0] for k, v in grid.items()}, n_eval)
        sel, ev = selection_keys(sweep), evaluation_keys(ecfg)
        assert len(sel) == sweep.num_seeds and len(ev) == 30 and not sel & ev


def test_the_protocol_uses_the_papers_settings_and_ceilings():
    # the paper's tables as printed: RockSample 11's 8 environments per seed, embed 256; rewards scaled as the
    # original implementation's environment factory scales RockSample's (and no other discrete environment's)
    gru = next(a for a in protocol_agents("rocksample_11_11", ("gru",)) if a.name == "gru")
    cfg, _ = protocol_config("rocksample_11_11", gru, "paper")
    assert (cfg.num_envs, cfg.normalize_reward, cfg.embed_size, cfg.total_steps) == (8, True, 256, 5_000_000)
    for env in ("tmaze_10", "battleship_10"):
        assert not protocol_config(env, next(iter(protocol_agents(env, ("gru",)))), "paper")[0].normalize_reward
    assert spec("battleship_10").protocol()["selection_seeds"] == 10
    assert protocol_config("rocksample_15_15", gru, "paper")[0].total_steps == 5_000_000
    # Battleship's ceiling is the probability-search policy's value: not trained; the registry's trained one is extra
    names = [a.name for a in protocol_agents("battleship_10", ("floor", "ceiling"))]
    assert names == ["floor", EXTRA_CEILING]
    # the mazes' ceiling is the paper's map; the registry's perfect_memory ceiling is the extra row
    maze = {a.name: a for a in protocol_agents("Navix-DMLab-Maze-01-v0", ("ceiling",))}
    assert maze["ceiling"].observability == "full" and maze[EXTRA_CEILING].observability == "perfect_memory"
    assert [a.name for a in protocol_agents("tmaze_10", ("ceiling",))] == ["ceiling"]  # the paper's = registry's
    ld = next(a for a in protocol_agents("tmaze_10", ("ld",)))
    assert protocol_config("tmaze_10", ld, "paper")[0].ld_weight == PAPER_LD_GRID["ld_weight"]
    assert PAPER_GRID["lr"] == (2.5e-3, 2.5e-4, 2.5e-5, 2.5e-6)


def test_the_smoke_protocol_sweeps_each_axis_ends_and_optimises_map_cnn_programs():
    """At `smoke` the protocol sweeps each axis's first and last value, on seeds still disjoint from the
    evaluation's; programs with a CNN encoder roll out 16 steps, and those of a map's FullImageCNN keep XLA's
    optimisations (unoptimised CPU convolutions over a map cost more than the compile time saved), the others
    (a first-person view's SmallImageCNN too) compile fast."""
    for env in ("tmaze_10", "Navix-DMLab-Maze-01-v0"):
        for agent in protocol_agents(env, ("floor", "ld", "trxl", "ceiling")):
            cfg, n_eval = protocol_config(env, agent, "smoke")
            validate(cfg)
            grid = spec(env).protocol()["ld_grid" if agent.double_critic else "grid"]
            assert {k: tuple(getattr(cfg, k)) for k in grid} == {k: (v[0], v[-1]) for k, v in grid.items()}
            assert len(cfg.grid()) == 2 ** len(grid)
            ecfg = evaluation_config(cfg, {k: v[0] for k, v in grid.items()}, n_eval)
            assert not selection_keys(cfg) & evaluation_keys(ecfg)
            cnn = env != "tmaze_10" and agent.name != EXTRA_CEILING  # the first-person view, the full map
            map_cnn = cnn and agent.name == "ceiling"
            assert cfg.fast_compile is not map_cnn, (env, agent.name)
            assert cfg.num_updates == 3 and cfg.num_steps == (16 if cnn else 64), (env, agent.name)


def test_a_sweep_with_no_finished_episode_selects_only_at_smoke():
    nan = float("nan")
    sets = [{"lr": lr, "lambda0": 0.5, "disc_return_auc": {"mean": nan}} for lr in (2.5e-3, 2.5e-4)]
    summary = {"sets": sets, "best_by_auc": 1}
    with pytest.raises(ProtocolError, match="finished an episode"):
        select(summary, {"lr": (), "lambda0": ()}, "here")
    assert select(summary, {"lr": (), "lambda0": ()}, "here", unfinished_ok=True) == {"lr": 2.5e-3, "lambda0": 0.5}


def test_intervals_follow_the_number_of_seeds():
    rng = np.random.default_rng(0)
    few, many = rng.normal(size=5), rng.normal(size=12)
    assert mean_ci(few)["ci_method"] == "student-t" and mean_ci(many)["ci_method"] == "bootstrap"
    m, lo, hi = student_t_ci([1.0, 2.0, 3.0])
    assert m == 2.0 and np.isclose(hi - m, 4.3027 * 1.0 / np.sqrt(3))
    ci = lambda v: {"mean": float(np.mean(v)), "ci_low": min(v), "ci_high": max(v), "per_seed": list(v)}  # noqa: E731
    four = {"floor": ci([0, 0, 0, 0]), "gru": ci([5, 5, 5, 5]), "ceiling": ci([9, 9, 9, 9])}
    assert gap_verdict(four)["holds"] is None and "fewer than 5 seeds" in gap_verdict(four)["reasons"][0]
    five = {k: ci(v["per_seed"] + [v["per_seed"][0]]) for k, v in four.items()}
    assert gap_verdict(five)["holds"] is True


@pytest.mark.slow
def test_protocol_benchmark_end_to_end(tmp_path):
    """A tiny protocol (T-Maze 5, two agents, a 2 × 2 grid): each record is the evaluation of the set its sweep
    selected by AUC, on seeds the sweep did not use, with the sweep table beside it."""
    out = tmp_path / "b"
    overrides = dict(hidden_size=8, num_envs=4, num_steps=16, num_minibatches=2, total_steps=4 * 16 * 3,
                     num_chunks=1, lr=(2.5e-3, 2.5e-4), lambda0=(0.5, 0.95), num_seeds=3)
    run_benchmark(("tmaze_5",), budget="smoke", out=out, agents=("floor", "ceiling"), overrides=overrides,
                  progress=False, protocol="paper")
    for name in ("floor", "ceiling"):
        rec = json.loads((out / "agents" / "tmaze_5" / f"{name}.json").read_text())
        sel = rec["selection"]
        assert rec["protocol"] == "paper" and len(sel["sets"]) == 4 and rec["num_seeds"] == 3
        best = max(sel["sets"], key=lambda s: s["auc"])
        assert sel["selected"] == {"lr": best["lr"], "lambda0": best["lambda0"]}
        assert rec["config"]["lr"] == [best["lr"]] and rec["evaluation"]["seed"] != sel["seed"]
        assert (out / "agents" / "tmaze_5" / f"{name}.sweep.csv").read_text().count("\n") == 5
    with pytest.raises(ValueError, match="protocol"):  # one output directory holds one protocol
        run_benchmark(("tmaze_5",), budget="smoke", out=out, agents=("floor",), progress=False)


def test_a_sweep_splits_into_programs_that_cover_its_grid_once():
    from pobax.eval._protocol import PART_ENV_STEPS, sweep_parts

    for env in ("tmaze_10", "rocksample_11_11", "battleship_10"):
        for agent in protocol_agents(env, ("gru", "ld")):
            cfg, _ = protocol_config(env, agent, "paper")
            grid = spec(env).protocol()["ld_grid" if agent.double_critic else "grid"]
            parts = sweep_parts(cfg, grid)
            sets = [tuple(hp[k] for k in grid) for _, p in parts for hp in p.grid()]
            assert sorted(sets) == sorted(tuple(hp[k] for k in grid) for hp in cfg.grid())  # each set once
            assert len({name for name, _ in parts}) == len(parts)
            for _, p in parts:
                assert p.num_updates * p.steps_per_update * p.num_seeds * len(p.grid()) <= PART_ENV_STEPS
                assert p.num_seeds == cfg.num_seeds and p.seed == cfg.seed  # a set's seeds are never split
            assert (len(parts) == 1) == (env == "tmaze_10")
            assert sweep_parts(cfg, grid, None) == [("all", cfg)]


@pytest.mark.slow  # 42 s on 2 cores
def test_a_sweep_in_parts_selects_as_one_program(tmp_path, capsys):
    """The same protocol with its sweep in four programs (one set each) and in one: the same table, the same
    selection, the same evaluation; the parts' directories are kept, and a finished part is reused."""
    overrides = dict(hidden_size=8, num_envs=4, num_steps=16, num_minibatches=2, total_steps=4 * 16 * 3,
                     num_chunks=1, lr=(2.5e-3, 2.5e-4), lambda0=(0.5, 0.95), num_seeds=3)
    kw = dict(budget="smoke", agents=("floor",), overrides=overrides, protocol="paper")
    run_benchmark(("tmaze_5",), out=tmp_path / "whole", progress=False, part_steps=None, **kw)
    run_benchmark(("tmaze_5",), out=tmp_path / "parts", dry_run=True, part_steps=600, **kw)
    assert "(sweep: 0 of 4 programs done)" in capsys.readouterr().out
    run_benchmark(("tmaze_5",), out=tmp_path / "parts", progress=False, part_steps=600, **kw)
    whole, parts = (json.loads((tmp_path / d / "agents" / "tmaze_5" / "floor.json").read_text())
                    for d in ("whole", "parts"))
    assert parts["selection"]["selected"] == whole["selection"]["selected"]
    for a, b in zip(parts["selection"]["sets"], whole["selection"]["sets"], strict=True):
        assert (a["lr"], a["lambda0"]) == (b["lr"], b["lambda0"]) and np.isclose(a["auc"], b["auc"], rtol=1e-3)
    assert parts["disc"]["per_seed"] == whole["disc"]["per_seed"]
    sweep = tmp_path / "parts" / "runs" / "tmaze_5" / "floor-sweep"
    assert {p.name for p in sweep.iterdir()} == {"lr=0.0025+lambda0=0.5", "lr=0.0025+lambda0=0.95",
                                                 "lr=0.00025+lambda0=0.5", "lr=0.00025+lambda0=0.95"}
    (tmp_path / "parts" / "agents" / "tmaze_5" / "floor.json").unlink()  # the record again, from the parts
    run_benchmark(("tmaze_5",), out=tmp_path / "parts", dry_run=True, part_steps=600, **kw)
    plan = capsys.readouterr().out  # every program done (the evaluation's too): the record is made from them
    assert "(sweep: 4 of 4 programs done; 0 GPU min left)" in plan and "env steps left to train: 0 (of " in plan
    run_benchmark(("tmaze_5",), out=tmp_path / "parts", dry_run=True, part_steps=600,
                  **{**kw, "agents": ("floor", "ceiling")})
    plan = capsys.readouterr().out  # the memoryless ceiling, of the floor's sizes, estimated at the floor's rate
    assert "(sweep: 0 of 4 programs done; ~" in plan and "GPU min left at floor's rate" in plan
    assert "GPU time left" in plan  # the ceiling's, at the rate the floor's finished parts trained
    for part in sweep.iterdir():  # as copied from another machine: the summary and configuration alone
        for f in part.iterdir():
            if f.name not in ("summary.json", "config.json"):
                shutil.rmtree(f) if f.is_dir() else f.unlink()
    run_benchmark(("tmaze_5",), out=tmp_path / "parts", part_steps=600, **kw)
    printed = capsys.readouterr().out
    assert printed.count("reusing the finished sweep part") == 4 and "reusing the finished run" in printed
    assert json.loads((tmp_path / "parts" / "agents" / "tmaze_5" / "floor.json").read_text())["selection"] == \
        parts["selection"]
    # parts trained elsewhere, merged into another directory: the protocol continues there from them
    from pobax.eval import merge_results

    (tmp_path / "parts" / "agents" / "tmaze_5" / "floor.json").unlink()
    merged = merge_results(tmp_path / "merged", (tmp_path / "parts",))
    assert merged["added"] == [] and len(merged["parts"]) == 4
    assert merge_results(tmp_path / "merged", (tmp_path / "parts",))["parts"] == []  # never over a part it has
    calls = json.loads((tmp_path / "merged" / "benchmark.json").read_text())["calls"]
    assert len([c for c in calls if "merged_from" in c]) == len(
        json.loads((tmp_path / "parts" / "benchmark.json").read_text())["calls"])  # a call is listed once
    # a part this directory began but did not finish is superseded by a finished one of the same configuration...
    unfinished = tmp_path / "merged" / "runs" / "tmaze_5" / "floor-sweep" / "lr=0.0025+lambda0=0.5"
    (unfinished / "summary.json").unlink()
    assert merge_results(tmp_path / "merged", (tmp_path / "parts",))["parts"] == ["tmaze_5/floor-sweep/"
                                                                                 "lr=0.0025+lambda0=0.5"]
    assert (unfinished / "summary.json").is_file()
    # ...never by one of another configuration under its name
    (unfinished / "summary.json").unlink()
    changed = json.loads((unfinished / "config.json").read_text())
    changed["config"]["total_steps"] += 1
    (unfinished / "config.json").write_text(json.dumps(changed))
    result = merge_results(tmp_path / "merged", (tmp_path / "parts",))
    assert result["parts"] == [] and result["kept_parts"] == ["tmaze_5/floor-sweep/lr=0.0025+lambda0=0.5"]
    assert not (unfinished / "summary.json").exists()
    shutil.copy(sweep / "lr=0.0025+lambda0=0.5" / "config.json", unfinished / "config.json")
    # ...nor while another process trains it there (was written into under its lock)
    from pobax.eval import RunDir

    (training := RunDir(unfinished)).hold()
    try:
        result = merge_results(tmp_path / "merged", (tmp_path / "parts",))
    finally:
        training.release()
    assert result["parts"] == [] and result["why"] == [
        f"left sweep part tmaze_5/floor-sweep/lr=0.0025+lambda0=0.5 to the process training it in {str(unfinished)!r}"]
    assert not (unfinished / "summary.json").exists()
    merge_results(tmp_path / "merged", (tmp_path / "parts",))
    run_benchmark(("tmaze_5",), out=tmp_path / "merged", part_steps=600, **kw)
    assert capsys.readouterr().out.count("reusing the finished sweep part") == 4
    again = json.loads((tmp_path / "merged" / "agents" / "tmaze_5" / "floor.json").read_text())
    assert again["selection"] == parts["selection"] and again["disc"]["per_seed"] == parts["disc"]["per_seed"]
    # a finished protocol record merged elsewhere brings its sweep table
    assert merge_results(tmp_path / "third", (tmp_path / "merged",))["added"] == ["tmaze_5/floor"]
    table = tmp_path / "third" / "agents" / "tmaze_5" / "floor.sweep.csv"
    assert table.read_text() == (tmp_path / "merged" / "agents" / "tmaze_5" / "floor.sweep.csv").read_text()
    assert len(table.read_text().splitlines()) == 1 + 4



@pytest.mark.slow
def test_a_sweep_continues_at_the_split_its_finished_parts_had(tmp_path, capsys):
    """A protocol resumed with another --part-steps (here: one program) reuses the finished parts of the split that
    made them instead of training the grid again under other names; parts no split reproduces are refused."""
    overrides = dict(hidden_size=8, num_envs=4, num_steps=16, num_minibatches=2, total_steps=4 * 16 * 3,
                     num_chunks=1, lr=(2.5e-3, 2.5e-4), lambda0=(0.5, 0.95), num_seeds=2)
    kw = dict(budget="smoke", agents=("floor",), overrides=overrides, protocol="paper")
    run_benchmark(("tmaze_5",), out=tmp_path / "b", progress=False, part_steps=400, **kw)
    sweep = tmp_path / "b" / "runs" / "tmaze_5" / "floor-sweep"
    parts = sorted(p.name for p in sweep.iterdir())
    assert len(parts) == 4
    (tmp_path / "b" / "agents" / "tmaze_5" / "floor.json").unlink()
    capsys.readouterr()
    run_benchmark(("tmaze_5",), out=tmp_path / "b", dry_run=True, part_steps=None, **kw)
    printed = capsys.readouterr().out
    assert "continuing its sweep's split" in printed and "(sweep: 4 of 4 programs done" in printed
    run_benchmark(("tmaze_5",), out=tmp_path / "b", part_steps=None, **kw)
    assert capsys.readouterr().out.count("reusing the finished sweep part") == 4
    assert sorted(p.name for p in sweep.iterdir()) == parts  # no "all" part trained beside them
    (tmp_path / "b" / "agents" / "tmaze_5" / "floor.json").unlink()
    (sweep / parts[0]).rename(sweep / "lr=9")
    with pytest.raises(BenchmarkError, match="no split of the sweep reproduces"):
        run_benchmark(("tmaze_5",), out=tmp_path / "b", dry_run=True, **kw)

TINY = ["--hidden-size", "8", "--num-envs", "4", "--num-steps", "16", "--num-minibatches", "2", "--total-steps",
        "192", "--num-chunks", "1", "--lr", "2.5e-3", "2.5e-4", "--lambda0", "0.5", "0.95", "--num-seeds", "3"]


@pytest.mark.slow
def test_gap_by_the_papers_protocol_from_the_command_line(tmp_path, capsys):
    import cli

    cli.main(["gap", "--env", "tmaze_5", "--protocol", "paper", "--agents", "floor", "--out", str(tmp_path / "g"),
              "--quiet", *TINY])
    rec = json.loads((tmp_path / "g" / "agents" / "tmaze_5" / "floor.json").read_text())
    assert rec["protocol"] == "paper" and len(rec["selection"]["sets"]) == 4 and rec["num_seeds"] == 3
    assert "floor" in capsys.readouterr().out


@pytest.mark.slow
def test_sweep_parts_train_side_by_side(tmp_path, capsys, monkeypatch):
    """--jobs 2: the sweep's parts in processes of their own, the evaluation once every part has finished; the
    record is the one a single process writes."""
    import cli

    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE", raising=False)
    args = ["benchmark", "--envs", "tmaze_5", "--protocol", "paper", "--budget", "smoke", "--agents", "floor", *TINY]
    cli.main([*args, "--out", str(tmp_path / "side"), "--jobs", "2", "--part-steps", "600"])
    printed = capsys.readouterr().out
    part = "== finished tmaze_5: floor (memoryless, partial), sweep part"
    assert printed.count(part) == 4
    assert printed.index("== started tmaze_5: floor (memoryless, partial) (log") > printed.rindex(part)
    cli.main([*args, "--out", str(tmp_path / "one"), "--jobs", "1", "--part-steps", "0"])
    side, one = (json.loads((tmp_path / d / "agents" / "tmaze_5" / "floor.json").read_text()) for d in ("side", "one"))
    assert side["selection"]["selected"] == one["selection"]["selected"]
    assert side["disc"]["per_seed"] == one["disc"]["per_seed"]


VERSION = "import importlib.util, sys; s = importlib.util.spec_from_file_location('v', sys.argv[1]); " \
          "m = importlib.util.module_from_spec(s); s.loader.exec_module(m); print(m.commit())"


def _commit(root: Path, env: dict | None = None) -> str:
    out = subprocess.run([sys.executable, "-c", VERSION, str(root / "pobax" / "_version.py")], capture_output=True,
                         text=True, timeout=60, env=env)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_the_commit_is_read_by_the_package_dirty_and_archived(tmp_path):
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    repo = tmp_path / "repo"
    (repo / "pobax").mkdir(parents=True)
    for name in ("_version.py", "_commit.txt"):
        shutil.copy(ROOT / "pobax" / name, repo / "pobax" / name)
    shutil.copy(ROOT / ".gitattributes", repo / ".gitattributes")
    git = lambda *a: subprocess.run(["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t", *a],  # noqa: E731
                                    check=True, capture_output=True, text=True).stdout.strip()
    git("init", "-q")
    git("add", ".")
    git("commit", "-q", "-m", "x")
    head = git("rev-parse", "--short=12", "HEAD")
    import os
    env = dict(os.environ, POBAX_COMMIT="something-else")  # no variable sets it
    assert _commit(repo, env) == head
    other = tmp_path / "other"  # nor git's own: GIT_DIR (set inside git hooks) named another repository's commit
    other.mkdir()
    subprocess.run(["git", "-C", str(other), "init", "-q"], check=True)
    subprocess.run(["git", "-C", str(other), "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q",
                    "--allow-empty", "-m", "y"], check=True)
    assert _commit(repo, dict(os.environ, GIT_DIR=str(other / ".git"), GIT_WORK_TREE=str(other))) == head
    (repo / "pobax" / "_version.py").write_text((repo / "pobax" / "_version.py").read_text() + "\n# edited\n")
    assert _commit(repo) == head + "-dirty"
    archive = tmp_path / "archive"
    archive.mkdir()
    tar = subprocess.run(["git", "-C", str(repo), "archive", "HEAD"], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(archive)], input=tar, check=True)
    assert _commit(archive) == head + "-archive"
    (archive / "pobax" / "_commit.txt").unlink()
    assert _commit(archive).startswith("version-")


def test_a_suite_under_the_papers_protocol_holds_the_papers_environments_only():
    """Maze 03 (left out of the paper's benchmark) and the masked MuJoCo environments the paper does not benchmark
    leave a suite under the paper's protocol, and are named; under the registry's, and named one by one, they
    stay."""
    names, left = resolve_envs(suite="discrete", protocol="paper")
    assert "Navix-DMLab-Maze-03-v0" in left and "Navix-DMLab-Maze-03-v0" not in names
    assert set(names) == set(SUITES["discrete"]) & set(SUITES["paper"]) and "tmaze_10" in names
    assert resolve_envs(suite="discrete")[0] == SUITES["discrete"]
    assert resolve_envs(("Navix-DMLab-Maze-03-v0",), protocol="paper") == (("Navix-DMLab-Maze-03-v0",), ())
    names, left = resolve_envs(suite="heavy", protocol="paper")
    assert {"Ant-V-v0", "Hopper-V-v0"} <= set(left) and "Walker-V-v0" in names
