"""`pobax benchmark`: the five agents per environment at a budget, one results table and figure, resumable."""

import csv
import json

import numpy as np
import pytest

import cli
from pobax.agent._presets import paper_preset
from pobax.env import SUITES, spec
from pobax.eval import AGENTS, CSV_COLUMNS, BenchmarkError, benchmark_plan, run_benchmark
from pobax.eval._report import read_rows
from pobax.eval._run import ConfigMismatchError

from _traces import count_traces


def test_plan_follows_the_registry_and_its_budgets():
    plan = benchmark_plan(SUITES["discrete"], "reduced")
    assert len(plan) == 7 * 5  # seven environments × five agents (maze 03 has no paper table: defaults)
    by = {(e.env, e.agent.name): e.config for e in plan}
    assert by[("tmaze_10", "gru")].num_seeds == 30 and by[("tmaze_10", "gru")].total_steps == 1_000_000
    assert by[("rocksample_15_15", "ld")].total_steps == 5_000_000 and by[("rocksample_15_15", "ld")].double_critic
    assert by[("battleship_10", "ceiling")].observability == "perfect_memory"
    assert by[("Navix-DMLab-Maze-02-v0", "trxl")].num_seeds == 5
    heavy = {(e.env, e.agent.name): e.config for e in benchmark_plan(("Walker-V-v0",), "reduced")}
    assert heavy[("Walker-V-v0", "gru")].num_envs == 64 and heavy[("Walker-V-v0", "gru")].total_steps == 5_000_000
    assert benchmark_plan(("Walker-V-v0",), "paper")[0].config.num_envs == 4  # the paper's own setting
    # `reduced` trains Walker-V's Transformer-XL at 2.5e-4; `paper` keeps its table's 2.5e-5.
    assert heavy[("Walker-V-v0", "trxl")].lr == (2.5e-4,)
    assert benchmark_plan(("Walker-V-v0",), "paper", ("trxl",))[0].config.lr == (2.5e-5,)
    pixels = benchmark_plan(("ant_pixels",), "reduced", ("gru",))[0].config
    assert (pixels.num_envs, benchmark_plan(("ant_pixels",), "paper", ("gru",))[0].config.num_envs) == (16, 4)
    # The pixel ceiling (Brax's state) normalises observations and rewards; pixel agents and the paper's table do not.
    plan = {e.agent.name: e.config for e in benchmark_plan(("halfcheetah_pixels",), "reduced", ("floor", "ceiling"))}
    assert {k: (c.normalize_obs, c.normalize_reward) for k, c in plan.items()} == {"floor": (False, False),
                                                                                 "ceiling": (True, True)}
    assert (plan["ceiling"].memory, plan["ceiling"].observability, plan["ceiling"].action_concat) == ("gru", "full", True)
    original = paper_preset("ant_pixels", "memoryless", "full", original=True)
    assert (original["normalize_obs"], original["normalize_reward"]) == (False, False)
    paper = {(e.env, e.agent.name): e.config for e in benchmark_plan(("rocksample_15_15",), "paper")}
    assert paper[("rocksample_15_15", "floor")].total_steps == 10_000_000 and paper[("rocksample_15_15", "floor")].num_seeds == 30
    assert spec("battleship_10").paper_figure["ld"] == 19.5 and spec("tmaze_5").paper_figure == {}
    with pytest.raises(BenchmarkError, match="Unknown budget"):
        benchmark_plan(("tmaze_10",), "huge")


def test_every_lambda_discrepancy_agent_of_the_suites_has_a_discrepancy_loss():
    """An 'ld' agent with β = 0 would be a GRU with two critics, reported as λ-discrepancy: every suite's has β > 0
    (maze 03 and untabled members of a family take a tabled member's λ1 and β), and β = 0 is refused."""
    for suite in ("discrete", "heavy"):
        for e in benchmark_plan(SUITES[suite], "reduced", ("ld",)):
            assert e.config.double_critic and min(e.config.ld_weight) > 0, e.env
    maze03 = benchmark_plan(("Navix-DMLab-Maze-03-v0",), "reduced", ("gru", "ld"))
    assert [e.config.action_concat for e in maze03] == [False, False]  # its GRU's settings, plus λ1 and β
    assert maze03[1].config.ld_weight == (0.25,) and maze03[1].config.lambda1 == (0.95,)
    with pytest.raises(ValueError, match="tmaze_5 has no λ-discrepancy setting"):
        benchmark_plan(("tmaze_5",), "smoke", ("ld",), overrides={"ld_weight": (0.0,)})
    for env in ("hopper_pixels", "rocksample_7_8", "Ant-P-v0", "battleship_6"):  # no paper table
        assert min(benchmark_plan((env,), "smoke", ("ld",))[0].config.ld_weight) > 0, env


@pytest.mark.slow
def test_smoke_benchmark_writes_the_results_and_resumes(tmp_path, capsys):
    out = tmp_path / "bench"
    cli.main(["benchmark", "--envs", "tmaze_5", "--budget", "smoke", "--out", str(out), "--quiet"])
    rows = list(csv.DictReader((out / "benchmark.csv").open()))
    assert list(rows[0].keys()) == list(CSV_COLUMNS)
    assert [r["agent"] for r in rows] == list(AGENTS)
    assert {r["budget"] for r in rows} == {"smoke"} and {r["device"] for r in rows} == {"cpu"}
    assert all(r["pobax_commit"] and r["jax_version"] for r in rows)
    ld = next(r for r in rows if r["agent"] == "ld")
    assert ld["double_critic"] == "true" and ld["memory"] == "gru"
    assert float(rows[0]["disc_ci_low"]) <= float(rows[0]["disc_mean"]) <= float(rows[0]["disc_ci_high"])
    md = (out / "benchmark.md").read_text()
    assert "## tmaze_5" in md and "Gap:" in md and (out / "benchmark.png").stat().st_size > 10_000
    records = sorted(p.name for p in (out / "agents" / "tmaze_5").glob("*.json"))
    assert records == sorted(f"{a}.json" for a in AGENTS)
    assert "tmaze_5" in capsys.readouterr().out
    # a second call trains nothing and changes no record; another budget in the same --out is refused
    before = {p: p.read_bytes() for p in (out / "agents").rglob("*.json")}
    with count_traces("_chunk_runs") as traces:
        result = run_benchmark(("tmaze_5",), budget="smoke", out=out, progress=False)
    assert traces[0] == 0 and len(result["rows"]) == 5
    assert {p: p.read_bytes() for p in (out / "agents").rglob("*.json")} == before
    with pytest.raises(ConfigMismatchError, match="total_steps"):
        run_benchmark(("tmaze_5",), budget="smoke", out=out, progress=False, overrides={"total_steps": 1024})
    assert len(json.loads((out / "benchmark.json").read_text())["calls"]) == 2


@pytest.mark.slow
def test_an_interrupted_agent_resumes_in_the_next_call(tmp_path, capsys):
    out, more = tmp_path / "bench", {"num_chunks": 3}

    def interrupted(chunk):
        raise KeyboardInterrupt  # Ctrl-C after the agent's first chunk

    with pytest.raises(BenchmarkError, match="on_chunk is called in this process"):  # not in jobs of their own
        run_benchmark(("tmaze_5",), budget="smoke", out=out, agents=("floor", "gru"), jobs=2, on_chunk=interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_benchmark(("tmaze_5",), budget="smoke", out=out, agents=("floor", "gru"), progress=False, overrides=more,
                      on_chunk=interrupted)
    run = out / "runs" / "tmaze_5" / "floor"
    assert json.loads((run / "checkpoint.json").read_text())["chunks_done"] == 1
    assert not (out / "agents" / "tmaze_5" / "floor.json").exists()
    calls = json.loads((out / "benchmark.json").read_text())["calls"]
    refused = r"runs/tmaze_5/floor' holds a run .* \(differs in: total_steps\)"
    with pytest.raises(ConfigMismatchError, match=refused):
        run_benchmark(("tmaze_5",), budget="smoke", out=out, agents=("floor", "gru"), progress=False,
                      overrides={**more, "total_steps": 4096})  # refused before anything is written
    assert json.loads((out / "benchmark.json").read_text())["calls"] == calls
    capsys.readouterr()
    run_benchmark(("tmaze_5",), budget="smoke", out=out, agents=("floor", "gru"), overrides=more, dry_run=True)
    plan = capsys.readouterr().out  # what is left: two thirds of the floor, the whole GRU
    steps = {e.agent.name: e.env_steps for e in benchmark_plan(("tmaze_5",), "smoke", ("floor", "gru"), overrides=more)}
    assert "to resume (1 of 3 chunks done)" in plan and "gru (partial)" in plan
    left = steps["floor"] - steps["floor"] // 3 + steps["gru"]
    assert f"env steps left to train: {left:,} (of {steps['floor'] + steps['gru']:,} in the plan)" in plan
    result = run_benchmark(("tmaze_5",), budget="smoke", out=out, agents=("floor", "gru"), progress=False,
                           overrides=more)
    assert [r["agent"] for r in result["rows"]] == ["floor", "gru"] and (run / "summary.json").exists()


def test_every_agent_has_its_own_colour_in_every_figure():
    from pobax.eval._plots import agent_color
    from pobax.memory import ZOO

    names = ["floor", "gru", "ld", "trxl", "ceiling", *ZOO]
    assert len({agent_color(n) for n in names}) == len(names)
    assert agent_color("lru (partial)") == agent_color("lru")  # a gap label's first word
    user = agent_color("my_cells:Trace")
    assert user == agent_color("my_cells:Trace") and user not in {agent_color(n) for n in names}


def test_curves_are_drawn_through_bins_where_no_episode_ended():
    """HalfCheetah's episodes all end together every 1000 steps, so most bins of its records' curves are empty
    (None): the figure's line and band join the bins that hold a value instead of breaking at every empty one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pobax.eval._plots import plot_band

    x = [10, 20, 30, 40, 50, 60]
    mean = [None, 1.0, None, None, 2.0, 3.0]
    low, high = [None, 0.5, None, None, 1.5, None], [None, 1.5, None, None, 2.5, 3.5]
    fig, ax = plt.subplots()
    line = plot_band(ax, x, mean, low, high, label="gru", color="C0")
    assert list(line.get_xdata()) == [20, 50, 60] and list(line.get_ydata()) == [1.0, 2.0, 3.0]
    (band,) = ax.collections  # the CI band covers the bins with both bounds: x 20 and 50
    xs = band.get_paths()[0].vertices[:, 0]
    assert np.isfinite(band.get_paths()[0].vertices).all() and set(xs) == {20.0, 50.0}
    plt.close(fig)


def test_reference_lines_far_above_the_curves_are_named_not_drawn():
    from pobax.eval._report import split_references

    lines = {"random policy return": 6.8, "oracle mean return": 57.8, "full information return": 87.0}
    near, far = split_references(lines, 5.0, 25.0)  # Battleship's curves: far lines would squeeze them
    assert near == {"random policy return": 6.8}
    assert far == {"oracle mean return": 57.8, "full information return": 87.0}
    assert split_references(lines, 0.0, 60.0) == ({"random policy return": 6.8, "oracle mean return": 57.8,
                                                    "full information return": 87.0}, {})


@pytest.mark.slow
def test_agents_side_by_side_train_as_in_one_process(tmp_path, capsys, monkeypatch):
    """--jobs 2: each agent in a process of its own (spawned, its output in runs/ENV/NAME.log), the same numbers
    as one process training them one after the other."""
    import os

    together = tmp_path / "jobs"
    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE", raising=False)  # restored after the test
    cli.main(["benchmark", "--envs", "tmaze_5", "--budget", "smoke", "--agents", "floor", "gru", "--out",
              str(together), "--jobs", "2"])
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"  # the jobs get the GPUs' memory
    printed = capsys.readouterr().out
    assert "== started tmaze_5: floor" in printed and "== finished tmaze_5: gru" in printed
    alone = run_benchmark(("tmaze_5",), budget="smoke", out=tmp_path / "one", agents=("floor", "gru"),
                          progress=False, jobs=1)
    assert [r["agent"] for r in alone["rows"]] == [r["agent"] for r in read_rows(together)] == ["floor", "gru"]
    for agent in ("floor", "gru"):
        a, b = (json.loads((d / "agents" / "tmaze_5" / f"{agent}.json").read_text())
                for d in (together, tmp_path / "one"))
        assert a["disc"]["per_seed"] == b["disc"]["per_seed"] and a["curve"] == b["curve"]
        assert "steps per run" in (together / "runs" / "tmaze_5" / f"{agent}.log").read_text()
    with pytest.raises(BenchmarkError, match="--jobs must be at least 1"):
        run_benchmark(("tmaze_5",), budget="smoke", out=tmp_path / "none", jobs=0)


@pytest.mark.slow
def test_side_by_side_jobs_report_failures_and_keep_going(tmp_path, monkeypatch):
    import os
    from types import SimpleNamespace

    from pobax.eval._parallel import Job, default_jobs, run_side_by_side, slot_environment

    gpus = [SimpleNamespace(platform="gpu", id=i, local_hardware_id=i) for i in range(2)]
    monkeypatch.setenv("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    assert default_jobs(gpus) == 2 and default_jobs(gpus[:1]) == 1
    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE")  # JAX's default: this process holds the GPUs' memory
    assert default_jobs(gpus) == 1
    monkeypatch.setenv("XLA_PYTHON_CLIENT_ALLOCATOR", "platform")  # allocates as needed: nothing held
    assert default_jobs(gpus) == 2
    assert default_jobs([SimpleNamespace(platform="cpu", id=i) for i in range(4)]) == 1
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    assert [s["CUDA_VISIBLE_DEVICES"] for s in slot_environment(gpus, 3)] == ["0", "1", "0"]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,3")  # this process sees the machine's GPUs 2 and 3 as 0 and 1
    assert [s["CUDA_VISIBLE_DEVICES"] for s in slot_environment(gpus, 3)] == ["2", "3", "2"]
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    assert slot_environment(gpus, 3)[0]["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
    assert "XLA_PYTHON_CLIENT_PREALLOCATE" not in slot_environment(gpus, 2)[0]
    done = []
    jobs = [Job("fails", os.chdir, (str(tmp_path / "missing"),), tmp_path / "fails.log"),
            Job("works", os.getcwd, (), tmp_path / "works.log")]
    failed = run_side_by_side(jobs, [{}, {}], progress=False, on_done=lambda job: done.append(job.label))
    assert [j.label for j in failed] == ["fails"] and done == ["works"]
    assert "FileNotFoundError" in (tmp_path / "fails.log").read_text()
    # a job waits for those it comes `after` (the inner directory needs the outer one); one after a failure never runs
    inner, outer = tmp_path / "outer" / "inner", tmp_path / "outer"
    jobs = [Job("inner", os.mkdir, (str(inner),), tmp_path / "inner.log", after=("outer",)),
            Job("after a failure", os.mkdir, (str(tmp_path / "never"),), tmp_path / "never.log", after=("fails",)),
            Job("fails", os.chdir, (str(tmp_path / "missing"),), tmp_path / "fails.log"),
            Job("outer", os.mkdir, (str(outer),), tmp_path / "outer.log")]
    failed = run_side_by_side(jobs, [{}, {}], progress=False)
    assert inner.is_dir() and not (tmp_path / "never").exists()
    assert sorted(j.label for j in failed) == ["after a failure", "fails"]


def test_a_killed_benchmark_ends_its_jobs(tmp_path):
    """SIGTERM (a `kill`, a scheduler's preemption) to the process running jobs side by side ends the jobs too,
    as Ctrl-C does, instead of leaving them training unwatched into directories that a rerun would resume."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    if not Path("/proc/self/stat").exists():
        pytest.skip("reads the process table from /proc")
    script = ("import sys, time\n"
              "from pathlib import Path\n"
              "from pobax.eval._parallel import Job, run_side_by_side\n"
              "if __name__ == '__main__':\n"
              "    d = Path(sys.argv[1])\n"
              "    run_side_by_side([Job('sleeps', time.sleep, (120,), d / 'job.log')], [{}], progress=True)\n")
    parent = subprocess.Popen([sys.executable, "-c", script, str(tmp_path)], stdout=subprocess.PIPE, text=True)

    def children():
        out = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                fields = stat.read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == parent.pid and fields[0] != "Z":
                out.append(int(stat.parent.name))
        return out

    assert parent.stdout.readline().startswith("== started sleeps")
    def jobs():  # the spawned job, not multiprocessing's resource tracker
        return [c for c in children()
                if "spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes().decode(errors="replace")]

    deadline = time.monotonic() + 60
    while not jobs() and time.monotonic() < deadline:
        time.sleep(0.2)
    (job,) = jobs()
    parent.send_signal(signal.SIGTERM)
    assert parent.wait(timeout=60) == 128 + signal.SIGTERM
    deadline = time.monotonic() + 30
    while Path(f"/proc/{job}").exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    gone = not Path(f"/proc/{job}").exists() or \
        Path(f"/proc/{job}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    assert gone, "the job outlived its benchmark"
    with pytest.raises(ProcessLookupError):
        os.kill(parent.pid, 0)


def test_verdicts_complete_saved_references_with_the_registrys():
    pytest.importorskip("navix")
    from pobax.eval._report import references, verdicts

    ci = lambda m: {"mean": m, "ci_low": m - 0.01, "ci_high": m + 0.01}  # noqa: E731
    # Records written before the mazes had a random-policy value: only the oracle's was saved.
    saved = {"optimal_discounted_return": 0.659}
    records = [{"env": "Navix-DMLab-Maze-02-v0", "agent": a, "metric": "disc_return", "disc": ci(m), "undisc": ci(m),
                "reference": dict(saved)} for a, m in (("floor", 0.072), ("gru", 0.21), ("ceiling", 0.035))]
    refs = references(records)["Navix-DMLab-Maze-02-v0"]
    assert refs["optimal_discounted_return"] == 0.659 and 0.02 < refs["random_policy_discounted_return"] < 0.05
    reasons = verdicts(records)["Navix-DMLab-Maze-02-v0"]["reasons"]
    assert "random policy's return" in reasons[0]
    # An environment this install does not know keeps what its records saved.
    unknown = [dict(r, env="not_an_env_7") for r in records]
    assert references(unknown) == {"not_an_env_7": saved}
    assert "ceiling below the floor" in verdicts(unknown)["not_an_env_7"]["reasons"][0]


def test_markdown_lists_the_episode_metrics_some_agent_reached():
    """Craftax's achievement success rates (an environment's `episode_metrics`) appear per environment, one column per
    agent, only the achievements that some agent unlocked."""
    from pobax.eval._report import format_markdown

    ci = lambda m: {"mean": m, "ci_low": m - 0.1, "ci_high": m + 0.1, "per_seed": [m]}  # noqa: E731
    base = dict(env="not_an_env_8", metric="return", budget="reduced", total_steps=100, num_seeds=1, paper_value=None,
                env_steps_per_s=1.0, device="cpu", pobax_commit="x", reference={})
    records = [dict(base, agent=a, label=a, disc=ci(r), undisc=ci(r),
                    episode_metrics={"achievement_collect_wood": ci(w), "achievement_eat_cow": ci(0.0),
                                     "achievement_place_table": ci(t)})
               for a, r, w, t in (("floor", 1.0, 0.5, 0.0), ("ceiling", 3.0, 0.9, 0.25))]
    md = format_markdown(records)
    assert "the 2 of 3 that some agent reached" in md
    assert "| metric | floor | ceiling |" in md
    assert "| achievement_collect_wood | 0.500 | 0.900 |" in md and "| achievement_place_table | 0.000 | 0.250 |" in md
    assert "eat_cow" not in md
    assert "Per-episode metrics" not in format_markdown([dict(r, episode_metrics={}) for r in records])


def test_a_record_names_every_device_and_commit_that_trained_its_run():
    """A run resumed elsewhere is recorded as trained on both machines (its sessions), in the order they trained;
    runs from before sessions were recorded keep their config.json's device."""
    from pobax.eval._benchmark import _trained_by

    summary = {"sessions": [{"device": "NVIDIA H200", "pobax_commit": "abc"},
                            {"device": "NVIDIA H100 80GB HBM3", "pobax_commit": "abc"},
                            {"device": "NVIDIA H200", "pobax_commit": "def"}]}
    assert _trained_by(summary, {"device": "old"}, "device") == "NVIDIA H200 + NVIDIA H100 80GB HBM3"
    assert _trained_by(summary, {}, "pobax_commit") == "abc + def"
    assert _trained_by({}, {"device": "NVIDIA H200"}, "device") == "NVIDIA H200"
    assert _trained_by({}, {}, "jax") == "unknown"


def test_merge_copies_other_directories_records_and_never_replaces_one(tmp_path, capsys):
    """`benchmark --merge` gathers records trained elsewhere (the shipped T-Maze records stand in for them) into
    --out and writes the results; a record --out has already is kept, and bad input is one line, exit 2, with the
    results already written untouched."""
    from pathlib import Path

    shipped = Path(__file__).resolve().parents[1] / "results" / "agents" / "tmaze_10"
    a, b, c, out = tmp_path / "a", tmp_path / "b", tmp_path / "c", tmp_path / "out"
    for src, names in ((a, ("gru",)), (b, ("gru", "floor")), (c, ("gru",))):
        (src / "agents" / "tmaze_10").mkdir(parents=True)
        (src / "benchmark.json").write_text(json.dumps({"envs": ["tmaze_10"], "calls": [{"command": f"from {src}"}]}))
        for n in names:
            record = json.loads((shipped / f"{n}.json").read_text())
            record["written"], record["wall_s"] = str(src), len(str(src))  # c's gru: a's training, written again
            if src == b:  # b's gru is another training than a's
                record["disc"] = {**record["disc"], "mean": record["disc"]["mean"] + 1}
            (src / "agents" / "tmaze_10" / f"{n}.json").write_text(json.dumps(record))
    cli.main(["benchmark", "--merge", str(a), str(b), str(c), "--out", str(out)])
    captured = capsys.readouterr()
    assert "merged 2 records" in captured.out
    assert captured.err == f"kept the record of tmaze_10/gru from {str(a)!r}, not {str(b)!r}'s (they differ in disc)\n"
    assert json.loads((out / "agents" / "tmaze_10" / "gru.json").read_text())["written"] == str(a)
    rows = list(csv.DictReader((out / "benchmark.csv").open()))
    assert [r["agent"] for r in rows] == ["floor", "gru"]
    meta = json.loads((out / "benchmark.json").read_text())
    assert [x.get("merged_from") for x in meta["calls"][:3]] == [str(a), str(b), str(c)]
    assert meta["envs"] == ["tmaze_10"] and meta["calls"][3]["added"] == ["tmaze_10/gru", "tmaze_10/floor"]
    before = (out / "benchmark.csv").read_bytes()
    paper = tmp_path / "paper"  # one output directory holds one protocol
    paper.mkdir()
    (paper / "benchmark.json").write_text(json.dumps({"envs": [], "calls": [], "protocol": "paper"}))
    for args, message in (([str(tmp_path / "nowhere")], "has no benchmark.json"),
                          ([str(a), "--envs", "tmaze_10"], "--merge trains nothing"),
                          ([str(paper)], "holds the 'paper' protocol's results")):
        with pytest.raises(SystemExit) as e:
            cli.main(["benchmark", "--merge", *args, "--out", str(out)])
        assert e.value.code == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1
    assert (out / "benchmark.csv").read_bytes() == before


def test_a_protocol_tables_sweep_csvs_are_rebuilt_from_their_records(tmp_path):
    """An edited or deleted `agents/ENV/NAME.sweep.csv` beside a protocol record: the tables were written from the
    records while the sweep table kept the edit; writing the results now writes it again from the (sealed) record."""
    import shutil
    from pathlib import Path

    from pobax.eval._report import write_results

    out = tmp_path / "protocol"
    shutil.copytree(Path(__file__).resolve().parents[1] / "results" / "protocol", out,
                    ignore=shutil.ignore_patterns("runs"))
    edited, gone = out / "agents" / "tmaze_10" / "floor.sweep.csv", out / "agents" / "tmaze_10" / "gru.sweep.csv"
    shipped = edited.read_text(), gone.read_text()
    edited.write_text(shipped[0].replace("0.0025,0.1,", "0.0025,0.1,9", 1))
    gone.unlink()
    write_results(out)
    assert (edited.read_text(), gone.read_text()) == shipped
    edited.write_bytes(b"\xff\xfe{")  # not UTF-8: was a UnicodeDecodeError traceback
    write_results(out)
    assert edited.read_text() == shipped[0]
