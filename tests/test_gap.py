"""The memory-improvability gap report: agents, outputs, reuse of finished agents, refusal to mix configs."""

import json

import pytest

from pobax.agent import ConfigError, paper_preset
from pobax.eval import format_gap, gap_report
from pobax.eval._gap import agent_config, gap_agents, gap_verdict
from pobax.eval._run import ConfigMismatchError

from _traces import count_traces

TINY = dict(hidden_size=8, num_envs=4, num_steps=16, num_minibatches=2, total_steps=4 * 16 * 3, num_seeds=2,
            num_chunks=1)


def test_gap_agents_follow_the_registry():
    names = [a.name for a in gap_agents("tmaze_10")]
    assert names == ["floor", "gru", "ld", "trxl", "ceiling"]
    labels = [a.label for a in gap_agents("tmaze_10")]
    assert labels[0] == "floor (memoryless, partial)" and labels[-1] == "ceiling (memoryless, full)"
    ld = gap_agents("tmaze_10")[2]
    assert ld.double_critic and ld.memory == "gru"
    cfg = agent_config("tmaze_10", ld)
    assert cfg.double_critic and cfg.ld_weight == (0.5,) and cfg.lambda1 == (0.95,)  # the paper's LD row
    rs = gap_agents("rocksample_11_11")[-1]
    assert (rs.memory, rs.observability) == ("gru", "perfect_memory")
    assert agent_config("rocksample_11_11", rs).num_envs == 32  # the registry's deviation (README)
    bs = gap_agents("battleship_10")[-1]
    assert (bs.name, bs.memory, bs.observability) == ("ceiling", "memoryless", "perfect_memory")
    assert [a.name for a in gap_agents("tmaze_10", ("floor", "ceiling"), memories=("gru", "other"))] == [
        "floor", "gru", "other", "ceiling"]
    # a memory named twice was two agents of one name: `gap` reported it twice, `benchmark` planned it twice
    assert [a.name for a in gap_agents("tmaze_10", ("floor", "floor"), memories=("lstm", "lstm", "s6"))] == [
        "floor", "lstm", "s6"]
    with pytest.raises(ValueError, match="Unknown agent 'lstm'"):
        gap_agents("tmaze_10", ("floor", "lstm"))


def test_gap_verdict():
    r = lambda m, lo, hi: {"mean": m, "ci_low": lo, "ci_high": hi}  # noqa: E731
    assert gap_verdict({"floor": r(1, 0.9, 1.1), "gru": r(2, 1.8, 2.2), "ceiling": r(3, 2.9, 3.1)})["holds"]
    overlap = gap_verdict({"floor": r(1, 0.9, 1.9), "gru": r(2, 1.8, 2.2), "ceiling": r(3, 2.9, 3.1)})
    assert overlap["holds"] is False and "gru" in overlap["reasons"][0]
    above = gap_verdict({"floor": r(1, 0.9, 1.1), "ld": r(3.5, 3.4, 3.6), "ceiling": r(3, 2.9, 3.1)})
    assert above["holds"] is False and "ld above the ceiling" in above["reasons"][-1]
    assert gap_verdict({"floor": r(1, 0.9, 1.1), "ceiling": r(3, 2.9, 3.1)})["holds"] is None  # no memory agent
    unlearned = gap_verdict({"floor": r(1, 0.9, 1.1), "gru": r(2, 1.8, 2.2), "ceiling": r(0.5, 0.4, 0.6)})
    assert unlearned["holds"] is False and "ceiling below the floor" in unlearned["reasons"][0]
    # A ceiling whose CI reaches the random policy's return has learned nothing, whatever the floor does.
    at_random = gap_verdict({"floor": r(1, 0.9, 1.1), "gru": r(2, 1.8, 2.2), "ceiling": r(0.5, 0.4, 0.6)}, random=0.45)
    assert at_random["holds"] is False and "random policy's return (0.45)" in at_random["reasons"][0]
    assert gap_verdict({"floor": r(1, 0.9, 1.1), "gru": r(2, 1.8, 2.2), "ceiling": r(3, 2.9, 3.1)}, random=0.5)["holds"]
    assert not gap_verdict({"floor": r(0.1, 0.05, 0.2), "gru": r(2, 1.8, 2.2), "ceiling": r(3, 0.3, 3.1)},
                           random=0.5)["holds"]
    nan = float("nan")
    assert gap_verdict({"floor": r(1, 0.9, 1.1), "gru": r(nan, nan, nan), "ceiling": r(3, 2.9, 3.1)})["holds"] is None


def test_maze_agents_use_the_papers_settings_and_perfect_memory_for_the_ceiling():
    pytest.importorskip("navix")
    agents = gap_agents("Navix-DMLab-Maze-01-v0")
    assert agents[-1].label == "ceiling (memoryless, perfect_memory, flatten)"
    ceiling = agent_config("Navix-DMLab-Maze-01-v0", agents[-1])
    assert (ceiling.memory, ceiling.observability, ceiling.encoder) == ("memoryless", "perfect_memory", "flatten")
    gru = agent_config("Navix-DMLab-Maze-01-v0", agents[1])
    assert gru.hidden_size == 512 and gru.num_envs == 256 and gru.lambda0 == (0.9,) and gru.action_concat
    # `train --preset paper` on the full map trains the paper's ceiling flattened, `paper-original` as the paper did
    # (its CNN, through the `auto` rule); the partial view's agents keep the rule.
    assert paper_preset("Navix-DMLab-Maze-02-v0", "memoryless", "full")["encoder"] == "flatten"
    assert paper_preset("Navix-DMLab-Maze-02-v0", "memoryless", "full", original=True)["encoder"] == "auto"
    assert "encoder" not in paper_preset("Navix-DMLab-Maze-02-v0", "memoryless")
    assert "encoder" not in paper_preset("tmaze_10", "memoryless", "full")


@pytest.mark.slow
def test_gap_report_writes_and_reuses_finished_agents(tmp_path):
    out = tmp_path / "gap"
    agents = ("floor", "gru", "ceiling")
    report = gap_report("tmaze_5", agents=agents, overrides=TINY, out=out, progress=False)
    assert [a["agent"] for a in report["agents"]] == ["floor (memoryless, partial)", "gru (partial)",
                                                      "ceiling (memoryless, full)"]
    saved = json.loads((out / "gap.json").read_text())
    assert saved["agents"][1]["disc_return"]["mean"] == report["agents"][1]["disc_return"]["mean"]
    assert (out / "gap.png").stat().st_size > 0 and "optimal" in " ".join(saved["reference"])
    assert saved["gap"]["holds"] in (True, False, None)
    text = format_gap(report)
    assert "floor" in text and "gap (discounted)" in text
    with count_traces("_chunk_runs") as traces:
        again = gap_report("tmaze_5", agents=agents, overrides=TINY, out=out, progress=False)
    assert traces[0] == 0  # nothing trained again
    assert [a["disc_return"] for a in again["agents"]] == [a["disc_return"] for a in report["agents"]]
    with pytest.raises(ConfigMismatchError, match="hidden_size"):
        gap_report("tmaze_5", agents=agents, overrides={**TINY, "hidden_size": 16}, out=out, progress=False)


@pytest.mark.slow
def test_gap_agents_can_be_trained_apart_and_assembled(tmp_path):
    out = tmp_path / "gap"
    part = gap_report("tmaze_5", agents=("floor",), overrides=TINY, out=out, progress=False)
    assert [a["agent"] for a in part["agents"]] == ["floor (memoryless, partial)"]
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["floor"]
    floor_written = (out / "floor" / "summary.json").stat().st_mtime_ns
    whole = gap_report("tmaze_5", agents=("floor", "ld", "ceiling"), overrides=TINY, out=out, progress=False)
    assert (out / "floor" / "summary.json").stat().st_mtime_ns == floor_written  # reused, not trained again
    assert all((out / a / "summary.json").exists() for a in ("ld", "ceiling"))
    assert whole["agents"][0]["disc_return"] == part["agents"][0]["disc_return"]
    assert json.loads((out / "ld" / "config.json").read_text())["config"]["double_critic"]
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["ceiling", "floor", "ld"]
    again = gap_report("tmaze_5", agents=("ceiling",), overrides=TINY, out=out, progress=False)
    assert [a["name"] for a in again["agents"]] == ["floor", "ld", "ceiling"]  # a subset adds to gap.json, never
    assert again["gap"] == whole["gap"] == json.loads((out / "gap.json").read_text())["gap"]  # shrinks it


def test_a_flag_one_agent_reads_does_not_part_the_others_from_the_report(tmp_path):
    """Agents trained apart (one process each) with the flags each reads: the GRU's `extra_dense`, which the floor
    refuses (it does not read it), keeps the floor trained without it in the GRU's report, and the floor's own call
    keeps the GRU."""
    out = tmp_path / "gap"
    gap_report("tmaze_5", agents=("floor",), overrides=TINY, out=out, progress=False)
    with_gru = gap_report("tmaze_5", agents=("gru",), overrides={**TINY, "extra_dense": True}, out=out, progress=False)
    assert [a["name"] for a in with_gru["agents"]] == ["floor", "gru"]
    assert json.loads((out / "gru" / "config.json").read_text())["config"]["extra_dense"]
    again = gap_report("tmaze_5", agents=("floor",), overrides=TINY, out=out, progress=False)
    assert [a["name"] for a in again["agents"]] == ["floor", "gru"]


def test_an_unknown_override_is_refused_before_anything_trains(tmp_path):
    """`overrides={"total_step": ...}` (a typo) trained the preset's budget, 1M steps, silently."""
    with pytest.raises(ConfigError, match="'total_step' is not a TrainConfig field"):
        gap_report("tmaze_5", agents=("floor",), overrides={"total_step": 2048}, out=tmp_path / "g", progress=False)
    assert not (tmp_path / "g").exists()
