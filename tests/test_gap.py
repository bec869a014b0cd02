"""The memory-improvability gap report: agents, outputs, reuse of finished agents, refusal to mix configs."""

import json

import pytest

import pobax.agent._train as T
from pobax.eval import format_gap, gap_report
from pobax.eval._gap import GapConfigMismatchError, agent_config, gap_agents

TINY = dict(hidden_size=8, num_envs=4, num_steps=16, num_minibatches=2, total_steps=4 * 16 * 3, num_seeds=2,
            num_chunks=1)


def test_gap_agents_follow_the_registry():
    labels = [a.label for a in gap_agents("tmaze_10")]
    assert labels == ["floor (memoryless, partial)", "gru (partial)", "ceiling (memoryless, full)"]
    rs = gap_agents("rocksample_11_11")[-1]
    assert (rs.memory, rs.observability) == ("gru", "perfect_memory")
    assert [a.label for a in gap_agents("battleship_10")][-1] == "gru (partial)"  # programmatic ceiling only


def test_maze_agents_use_the_papers_settings_and_a_flattened_map_for_the_ceiling():
    pytest.importorskip("navix")
    agents = gap_agents("Navix-DMLab-Maze-01-v0")
    assert agents[-1].label == "ceiling (memoryless, full, flatten)"
    ceiling = agent_config("Navix-DMLab-Maze-01-v0", agents[-1])
    assert (ceiling.memory, ceiling.observability, ceiling.encoder) == ("memoryless", "full", "flatten")
    gru = agent_config("Navix-DMLab-Maze-01-v0", agents[1])
    assert gru.hidden_size == 512 and gru.num_envs == 256 and gru.lambda0 == (0.9,) and gru.action_concat


def test_gap_report_writes_and_reuses_finished_agents(tmp_path):
    out = tmp_path / "gap"
    report = gap_report("tmaze_5", overrides=TINY, out=out, progress=False)
    assert [a["agent"] for a in report["agents"]] == ["floor (memoryless, partial)", "gru (partial)",
                                                      "ceiling (memoryless, full)"]
    saved = json.loads((out / "gap.json").read_text())
    assert saved["agents"][1]["disc_return"]["mean"] == report["agents"][1]["disc_return"]["mean"]
    assert (out / "gap.png").stat().st_size > 0 and "optimal" in " ".join(saved["reference"])
    assert "floor" in format_gap(report)
    traces = T.TRACE_COUNT
    again = gap_report("tmaze_5", overrides=TINY, out=out, progress=False)
    assert T.TRACE_COUNT == traces  # nothing trained again
    assert [a["disc_return"] for a in again["agents"]] == [a["disc_return"] for a in report["agents"]]
    with pytest.raises(GapConfigMismatchError, match="hidden_size"):
        gap_report("tmaze_5", overrides={**TINY, "hidden_size": 16}, out=out, progress=False)


def test_gap_agents_can_be_trained_apart_and_assembled(tmp_path):
    out = tmp_path / "gap"
    with pytest.raises(ValueError, match="no agent 'trxl'.*floor, gru, ceiling"):
        gap_report("tmaze_5", overrides=TINY, out=out, progress=False, only=("trxl",))
    part = gap_report("tmaze_5", overrides=TINY, out=out, progress=False, only=("floor",))
    assert [a["agent"] for a in part["agents"]] == ["floor (memoryless, partial)"]
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["floor"]
    floor_written = (out / "floor" / "summary.json").stat().st_mtime_ns
    whole = gap_report("tmaze_5", overrides=TINY, out=out, progress=False)
    assert (out / "floor" / "summary.json").stat().st_mtime_ns == floor_written  # reused, not trained again
    assert all((out / a / "summary.json").exists() for a in ("gru", "ceiling"))
    assert whole["agents"][0]["disc_return"] == part["agents"][0]["disc_return"]
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["ceiling", "floor", "gru"]
