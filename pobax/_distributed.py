"""Several processes, one set of runs: JAX's multi-controller model.

Every process runs the same program on its own devices; a run lives on one device of one process (the runs are
sharded over `jax.devices()`, every device of every process). Values enter the program from the host, the same on
every process (`put`), and leave it gathered from every process (`fetch`). Process 0 writes the run directory; a
resume reads it in every process, so it must be on a file system they share.

    pobax.init_distributed("node0:12345", num_processes=2, process_id=0)   # in each process, before training
    pobax.train(cfg, out="runs/x")                                          # the same call in every process
"""

import jax
import numpy as np
from jax.experimental import multihost_utils


def init_distributed(coordinator: str | None = None, num_processes: int | None = None,
                     process_id: int | None = None) -> None:
    """Join the processes of a multi-process run (`jax.distributed.initialize`): call it in every process before
    anything else uses JAX. `coordinator` is process 0's HOST:PORT. Without arguments, JAX reads them from the
    cluster's environment (SLURM, Open MPI, ...) or from JAX_COORDINATOR_ADDRESS / JAX_NUM_PROCESSES /
    JAX_PROCESS_ID."""
    if (num_processes is None) != (process_id is None):
        raise ValueError("--num-processes and --process-id go together (or neither: read from the cluster).")
    if num_processes is not None and num_processes < 1:
        raise ValueError(f"--num-processes must be a positive integer (the processes of the run), got {num_processes}.")
    if num_processes is not None and not 0 <= process_id < num_processes:
        raise ValueError(f"--process-id must be in 0..{num_processes - 1}, got {process_id}.")
    host, sep, port = (coordinator or "").rpartition(":")
    if coordinator is not None and not (sep and host and port.isdigit() and 0 < int(port) < 65536):
        raise ValueError(f"--coordinator takes process 0's HOST:PORT (e.g. node0:1234), got {coordinator!r}.")
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id)


def is_lead() -> bool:
    """Whether this process writes results (process 0; the only process of a single-process run)."""
    return jax.process_index() == 0


def single_process(command: str) -> None:
    """Refuse `command` (sweep, gap, benchmark: they write files of their own) in a multi-process run."""
    if jax.process_count() > 1:
        raise ValueError(f"{command} runs in one process (over all its devices, `devices=`); in a multi-process run "
                         f"only `train` shares the runs among processes.")


def is_key(x) -> bool:
    """Whether `x` (an array or a `jax.ShapeDtypeStruct`) is a typed PRNG key array."""
    dtype = getattr(x, "dtype", None)
    return dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key)


def as_key_like(data, like):
    """Raw key data `data` as a typed key array like `like` (a key array, whose implementation it takes; or a shape
    of one: then the default implementation, which made the keys, `jax.random.key(seed)`). The one place that wraps
    keys: placing (`put`), gathering (`fetch`) and reading a checkpoint all move keys as their raw data."""
    impl = None if isinstance(like, jax.ShapeDtypeStruct) else jax.random.key_impl(like)
    return jax.random.wrap_key_data(data, impl=impl)


def put(tree, sharding):
    """`tree` placed with `sharding` (typed PRNG keys included); with several processes every process passes the same
    values."""
    def one(x):
        if is_key(x):
            return as_key_like(one(jax.random.key_data(x)), x)
        return jax.device_put(x, sharding)

    return jax.tree.map(one, tree)


def fetch(tree):
    """The values of `tree` on this host: arrays spread over several processes gathered from all of them (every
    process must call this at the same point), the others as they are."""
    def one(x):
        if not isinstance(x, jax.Array) or x.is_fully_addressable:
            return x
        if is_key(x):
            return as_key_like(one(jax.random.key_data(x)), x)
        return np.asarray(multihost_utils.process_allgather(x, tiled=True))

    return jax.tree.map(one, tree)
