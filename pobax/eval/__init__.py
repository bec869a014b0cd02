"""Running and judging: `train` (a run directory, checkpoints, a summary), sweeps, gap reports, the benchmark,
statistics over seeds and figures."""

from ._benchmark import CSV_COLUMNS as CSV_COLUMNS
from ._benchmark import BenchmarkError as BenchmarkError
from ._benchmark import benchmark_plan as benchmark_plan
from ._benchmark import read_rows as read_rows
from ._benchmark import run_benchmark as run_benchmark
from ._benchmark import write_results as write_results
from ._gap import AGENTS as AGENTS
from ._gap import PAPER_GRID as PAPER_GRID
from ._gap import PAPER_LD_GRID as PAPER_LD_GRID
from ._gap import format_gap as format_gap
from ._gap import gap_report as gap_report
from ._gap import gap_verdict as gap_verdict
from ._plots import curve_with_ci as curve_with_ci
from ._plots import plot_learning_curves as plot_learning_curves
from ._plots import plot_runs as plot_runs
from ._results import CheckpointError as CheckpointError
from ._results import OutputDirError as OutputDirError
from ._results import RunDir as RunDir
from ._results import RunDirExistsError as RunDirExistsError
from ._results import atomic_write_text as atomic_write_text
from ._results import list_runs as list_runs
from ._results import write_json as write_json
from ._run import Interrupted as Interrupted
from ._run import TrainResult as TrainResult
from ._run import train as train
from ._stats import auc as auc
from ._stats import bootstrap_ci as bootstrap_ci
from ._stats import final_value as final_value
from ._stats import iqm as iqm
from ._stats import summarize as summarize
from ._sweep import runs_per_program as runs_per_program
from ._sweep import sweep as sweep
from ._sweep import write_preset as write_preset
