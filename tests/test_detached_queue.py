"""`benchmarks/detached_queue.py`: lanes of commands run detached, and a benchmark's records packed for --merge."""

import importlib.util
import json
import sys
import tarfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("detached_queue", ROOT / "benchmarks" / "detached_queue.py")
dq = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(dq)


def test_queue_lines_are_lanes_in_order_and_a_bad_line_is_refused():
    lanes = dq.parse_queue("# GPU 0 first\n0: a --x 1\n\n1: b\n0: c: with a colon\n")
    assert lanes == {"0": ["a --x 1", "c: with a colon"], "1": ["b"]}
    for text, message in (("0 a", "line 1 is not"), ("x y: a", "line 1 is not"), ("0:", "line 1 is not"),
                          ("# nothing\n", "no commands")):
        with pytest.raises(dq.QueueError, match=message):
            dq.parse_queue(text)


def test_lanes_run_at_once_their_commands_in_order_detached(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(dq, "gpu_names", lambda: ["GPU A", "GPU B"])  # lane 1 is a GPU, whatever this machine has
    (tmp_path / "q.txt").write_text(
        "a: for i in $(seq 600); do test -f go && break; sleep 0.1; done; echo first > order.txt\n"  # waits for go
        "a: test -f order.txt && echo second >> order.txt; exit 3\n"  # runs after the first, whatever its status
        "1: echo $CUDA_VISIBLE_DEVICES $XLA_PYTHON_CLIENT_PREALLOCATE > env.txt\n")
    state = tmp_path / "state"
    assert dq.main(["start", "--state", str(state), "--queue", "q.txt"]) == 0
    # start returned while lane a's first command still waits: the queue runs in a session of its own
    assert not dq.read_status(state)["done"] and not (tmp_path / "order.txt").exists()
    (tmp_path / "go").touch()
    t0 = time.time()
    status = dq.wait(state, seconds=600, every=0.2, dirs=[], to=None)
    assert status["done"] and time.time() - t0 < 300  # wait ends with the queue, long before its deadline
    assert (tmp_path / "order.txt").read_text().split() == ["first", "second"]
    assert (tmp_path / "env.txt").read_text().split() == ["1", "false"]  # a numbered lane is that GPU
    assert [c["rc"] for c in status["lanes"]["a"]] == [0, 3] and status["lanes"]["1"][0]["rc"] == 0
    assert "== exit 3" in (state / "a.log").read_text()
    assert dq.main(["wait", "--state", str(state), "--seconds", "0"]) == 1  # a failed command: not exit 0
    # a finished queue's state may be reused; a running one's may not
    (tmp_path / "q2.txt").write_text("a: sleep 3\n")
    assert dq.main(["start", "--state", str(state), "--queue", "q2.txt"]) == 0
    assert dq.main(["start", "--state", str(state), "--queue", "q2.txt"]) == 2


def test_a_lane_naming_a_gpu_the_machine_lacks_is_refused(tmp_path, monkeypatch, capsys):
    (tmp_path / "q.txt").write_text("0: true\n1: true\n")
    monkeypatch.setattr(dq, "gpu_names", lambda: ["GPU A"])
    assert dq.main(["start", "--state", str(tmp_path / "s"), "--queue", str(tmp_path / "q.txt")]) == 2
    assert "lanes 1 name GPUs this machine lacks (it has 1)" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()  # nothing started


def _fake_benchmark(root: Path) -> None:
    for rel, text in (("benchmark.json", "{}"), ("benchmark.md", "# t"), ("agents/e/floor.json", "{}"),
                      ("agents/e/floor.sweep.csv", "a"), ("runs/e/floor-sweep/p1/summary.json", "{}"),
                      ("runs/e/floor-sweep/p1/config.json", "{}"), ("runs/e/floor-sweep/p1/sessions.json", "[]"),
                      ("runs/e/floor.log", "log"), ("runs/e/floor/checkpoint-00003.eqx", "weights"),
                      ("runs/e/floor/checkpoint.json", "{}"), ("runs/e/floor/metrics/00000.csv", "m")):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)


def test_pack_keeps_what_a_merge_needs_and_leaves_models(tmp_path):
    _fake_benchmark(tmp_path / "pA")
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "0.log").write_text("lane")
    to = tmp_path / "r.tgz"
    n = dq.pack([tmp_path / "pA", tmp_path / "not-yet"], to, tmp_path / "state")
    with tarfile.open(to) as tar:
        names = sorted(tar.getnames())
    assert names == sorted(["pA/benchmark.json", "pA/benchmark.md", "pA/agents/e/floor.json",
                            "pA/agents/e/floor.sweep.csv", "pA/runs/e/floor-sweep/p1/summary.json",
                            "pA/runs/e/floor-sweep/p1/config.json", "pA/runs/e/floor-sweep/p1/sessions.json",
                            "pA/runs/e/floor.log", "queue/0.log"]) and n == len(names)
    assert dq.pack([tmp_path / "pA"], to, metrics=True) == n  # + the metrics CSV, - the lane's log
    with tarfile.open(to) as tar:
        assert "pA/runs/e/floor/metrics/00000.csv" in tar.getnames()
        assert not any(m.endswith(".eqx") for m in tar.getnames())
    (tmp_path / "x").mkdir()
    _fake_benchmark(tmp_path / "x" / "pA")
    assert dq.main(["pack", str(tmp_path / "pA"), str(tmp_path / "x" / "pA"), "--to", str(to)]) == 2


def test_pack_refuses_a_target_it_did_not_write_and_a_directory_that_is_not_there(tmp_path, capsys):
    """`pack --to notes.txt` (and `wait --pack ... --to notes.txt`) replaced the file with a tarball; `pack
    nonexistent` wrote a tarball of nothing and said so with exit 0."""
    _fake_benchmark(tmp_path / "pA")
    notes = tmp_path / "notes.txt"
    notes.write_text("precious")
    (tmp_path / "d").mkdir()
    for args, message in (([str(tmp_path / "pA"), "--to", str(notes)], "holds another file (not a tarball"),
                          ([str(tmp_path / "pA"), "--to", str(tmp_path / "d")], "is a directory"),
                          ([str(tmp_path / "gone"), "--to", str(tmp_path / "r.tgz")], "nothing to pack in")):
        capsys.readouterr()
        assert dq.main(["pack", *args]) == 2
        assert message in capsys.readouterr().err
    assert notes.read_text() == "precious" and not (tmp_path / "r.tgz").exists()
    assert not list(tmp_path.glob("*.part")) and not list((tmp_path / "d").iterdir())
    assert dq.main(["pack", str(tmp_path / "pA"), "--to", str(tmp_path / "r.tgz")]) == 0
    assert dq.main(["pack", str(tmp_path / "pA"), "--to", str(tmp_path / "r.tgz")]) == 0  # its own tarball again


@pytest.mark.slow  # about 15 s on 2 cores: a smoke benchmark in a detached lane
def test_a_detached_benchmark_packs_into_a_mergeable_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    out, queue = tmp_path / "b", tmp_path / "q.txt"
    queue.write_text(f"cpu: JAX_PLATFORMS=cpu {sys.executable} cli.py benchmark --envs tmaze_5 --agents floor "
                     f"--budget smoke --quiet --out {out}\n")
    assert dq.main(["start", "--state", str(tmp_path / "s"), "--queue", str(queue)]) == 0
    to = tmp_path / "r.tgz"
    assert dq.main(["wait", "--state", str(tmp_path / "s"), "--seconds", "300", "--every", "1",
                    "--pack", str(out), "--to", str(to)]) == 0
    assert dq.read_status(tmp_path / "s")["lanes"]["cpu"][0]["rc"] == 0
    with tarfile.open(to) as tar:
        tar.extractall(tmp_path / "back")
    from pobax.eval import merge_results
    merged = merge_results(tmp_path / "merged", (tmp_path / "back" / "b",))
    assert merged["added"] == ["tmaze_5/floor"]
    record = json.loads((tmp_path / "merged" / "agents" / "tmaze_5" / "floor.json").read_text())
    assert record == json.loads((out / "agents" / "tmaze_5" / "floor.json").read_text())


@pytest.mark.slow
def test_a_cut_run_travels_in_the_checkpoint_tarball_and_resumes_exactly(tmp_path):
    from pobax.eval import run_benchmark
    more = {"num_chunks": 3}

    def interrupted(chunk):
        raise KeyboardInterrupt  # the call's end, after the first chunk

    with pytest.raises(KeyboardInterrupt):
        run_benchmark(("tmaze_5",), budget="smoke", out=tmp_path / "pA", agents=("floor",), progress=False,
                      overrides=more, on_chunk=interrupted)
    ck = tmp_path / "ck.tgz"
    assert dq.pack_checkpoints([tmp_path / "pA"], ck, max_bytes=1) == ([], ["pA/runs/tmaze_5/floor"])
    assert dq.pack_checkpoints([tmp_path / "pA", tmp_path / "none"], ck, 2**24) == (["pA/runs/tmaze_5/floor"], [])
    whole = ck.read_bytes()
    assert dq.pack_checkpoints([tmp_path / "pA"], ck, 2**24, piece_bytes=len(whole) // 3 + 1)[0]  # in 3 pieces
    pieces = sorted(tmp_path.glob("ck.tgz.*"))
    assert [p.name for p in pieces] == ["ck.tgz.00", "ck.tgz.01", "ck.tgz.02"] and not ck.exists()
    ck.write_bytes(b"".join(p.read_bytes() for p in pieces))  # cat ck.tgz.?? > ck.tgz
    with tarfile.open(ck) as tar:
        tar.extractall(tmp_path / "next")  # the next machine: only what the tarball holds
    dq.pack_checkpoints([tmp_path / "pA"], ck, 2**24)
    assert not list(tmp_path.glob("ck.tgz.*"))  # an earlier call's pieces go
    resumed = tmp_path / "next" / "pA"
    assert json.loads((resumed / "runs/tmaze_5/floor/checkpoint.json").read_text())["chunks_done"] == 1
    run_benchmark(("tmaze_5",), budget="smoke", out=resumed, agents=("floor",), progress=False, overrides=more)
    run_benchmark(("tmaze_5",), budget="smoke", out=tmp_path / "straight", agents=("floor",), progress=False,
                  overrides=more)
    assert (resumed / "runs/tmaze_5/floor/metrics.csv").read_bytes() == \
        (tmp_path / "straight/runs/tmaze_5/floor/metrics.csv").read_bytes()
    sessions = json.loads((resumed / "runs/tmaze_5/floor/sessions.json").read_text())
    assert len(sessions["sessions"] if isinstance(sessions, dict) else sessions) == 2
    assert dq.pack_checkpoints([resumed], ck, 2**24) == ([], [])  # finished: nothing left to resume


def test_a_damaged_state_or_bad_numbers_are_refused(tmp_path, capsys):
    """A damaged status.json, a queue file that is not text, and NaN or infinite --seconds / --max-mib were
    tracebacks (or, for --seconds nan, a wait that never returned)."""
    state = tmp_path / "q"
    state.mkdir()
    for text in ("{bad", '{"x": 1}'):
        (state / "status.json").write_text(text)
        assert dq.main(["status", "--state", str(state)]) == 2
        assert "is not a queue's status" in capsys.readouterr().err
    (tmp_path / "queue.txt").write_bytes(b"\xff: echo\n")
    assert dq.main(["start", "--state", str(tmp_path / "q2"), "--queue", str(tmp_path / "queue.txt")]) == 2
    assert "is not UTF-8 text" in capsys.readouterr().err
    for flag, value in (("--seconds", "nan"), ("--seconds", "inf"), ("--max-mib", "nan")):
        args = ["wait", "--state", str(state), "--seconds", "1", flag, value]
        assert dq.main(args) == 2, args
        assert "must be a finite number" in capsys.readouterr().err


def test_require_gpu_starts_nothing_on_another_kind(tmp_path, monkeypatch, capsys):
    """A Battleship sweep part trained on an H100 when no H200 came: with --require-gpu the queue does not start."""
    (tmp_path / "q.txt").write_text("0: true\n")
    monkeypatch.setattr(dq, "gpu_names", lambda: ["NVIDIA H100 80GB HBM3"])
    args = ["start", "--state", str(tmp_path / "s"), "--queue", str(tmp_path / "q.txt"), "--require-gpu", "H200"]
    assert dq.main(args) == 2
    assert "--require-gpu 'H200': this machine's GPUs are NVIDIA H100 80GB HBM3; nothing started" in \
        capsys.readouterr().err
    assert not (tmp_path / "s").exists()
    monkeypatch.setattr(dq, "gpu_names", lambda: None)  # no nvidia-smi: nothing to vouch for the kind
    assert dq.main(args) == 2 and "none that nvidia-smi lists" in capsys.readouterr().err
    monkeypatch.setattr(dq, "gpu_names", lambda: ["NVIDIA H200"])
    monkeypatch.chdir(tmp_path)
    assert dq.main(args) == 0
    assert dq.wait(tmp_path / "s", seconds=120, every=0.2, dirs=[], to=None)["done"]


def test_otherwise_starts_the_second_queue_on_another_kind(tmp_path, monkeypatch, capsys):
    """Probes that any GPU may train run where no H200 came; the protocol's queue runs only on one."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "protocol.txt").write_text("0: echo protocol > ran.txt\n")
    (tmp_path / "probes.txt").write_text("0: echo probes > ran.txt\n")
    args = ["start", "--state", "s", "--queue", "protocol.txt", "--require-gpu", "H200", "--otherwise", "probes.txt"]
    for names, ran in ((["NVIDIA H100 80GB HBM3"], "probes"), (["NVIDIA H200"], "protocol")):
        monkeypatch.setattr(dq, "gpu_names", lambda names=names: names)
        assert dq.main(args) == 0
        assert dq.wait(tmp_path / "s", seconds=120, every=0.2, dirs=[], to=None)["done"]
        assert (tmp_path / "ran.txt").read_text().split() == [ran]
    assert "GPUs are NVIDIA H100 80GB HBM3; starting --otherwise probes.txt" in capsys.readouterr().out
    monkeypatch.setattr(dq, "gpu_names", lambda: None)  # no nvidia-smi: lane 0 of either queue would be the CPU
    (tmp_path / "s" / "status.json").unlink()
    assert dq.main(args) == 2 and "--otherwise starts only where nvidia-smi lists GPUs" in capsys.readouterr().err
    monkeypatch.setattr(dq, "gpu_names", lambda: ["NVIDIA H100 80GB HBM3"])
    # both queues are checked before either starts; --otherwise alone is refused
    (tmp_path / "bad.txt").write_text("no lane here\n")
    for argv, message in (([*args[:-1], "bad.txt"], "line 1 is not"),
                          ([*args[:5], "--otherwise", "probes.txt"], "give --require-gpu too"),
                          ([*args[:-1], "missing.txt"], "missing.txt")):
        (tmp_path / "s" / "status.json").unlink(missing_ok=True)
        assert dq.main(argv) == 2, argv
        assert message in capsys.readouterr().err
        assert not (tmp_path / "s" / "status.json").exists()


def test_gpu_names_reads_nvidia_smi(monkeypatch):
    class Out:
        returncode, stdout = 0, ("GPU 0: NVIDIA H200 (UUID: GPU-1)\nGPU 1: NVIDIA H100 80GB HBM3 (UUID: GPU-2)\n"
                                 "  MIG 1g.10gb Device 0: (UUID: MIG-3)\n")

    monkeypatch.setattr(dq.subprocess, "run", lambda *a, **k: Out())
    assert dq.gpu_names() == ["NVIDIA H200", "NVIDIA H100 80GB HBM3"]


def test_a_packed_sweep_continues_on_the_next_machine_without_training(tmp_path):
    """A sweep into a packed directory came back without its marker: the same sweep in the unpacked copy was refused
    (the directory held runs but no `pobax-sweep.json`) or trained again. Packed with its metrics, the finished
    programs, the marker and the selection come back, and the same sweep picks up from them without training."""
    import dataclasses

    from pobax.agent import TrainConfig
    from pobax.eval import sweep

    cfg = TrainConfig(env="tmaze_5", memory="memoryless", hidden_size=8, num_envs=2, num_steps=8, num_minibatches=2,
                      total_steps=2 * 8 * 2, num_seeds=1, num_chunks=1, lr=(1e-3, 1e-2), fast_compile=True)
    first = sweep(cfg, tmp_path / "pr" / "runs" / "sw", max_runs=1, progress=False)
    dq.pack([tmp_path / "pr"], tmp_path / "r.tgz", metrics=True)
    with tarfile.open(tmp_path / "r.tgz") as tar:
        tar.extractall(tmp_path / "next", filter="data")
    moved = tmp_path / "next" / "pr" / "runs" / "sw"
    assert (moved / "pobax-sweep.json").is_file() and (moved / "best.json").is_file()

    def trained(chunk):
        raise AssertionError("the continued sweep trained")

    again = sweep(cfg, moved, max_runs=1, progress=False, on_chunk=trained)
    assert again["best"]["hyperparameters"] == first["best"]["hyperparameters"]
    assert len(again["programs"]) == 2
    with pytest.raises(ValueError):  # another sweep into it is still refused by the marker
        sweep(dataclasses.replace(cfg, lr=(1e-4,)), moved, progress=False)
