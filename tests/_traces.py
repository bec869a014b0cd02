"""Counting how often JAX traces a function, from JAX's own monitoring events (nothing in pobax counts)."""

import contextlib

import jax

_TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"


@contextlib.contextmanager
def count_traces(fun_name: str):
    """Within: `counter[0]` is the number of times a function named `fun_name` was traced for jit (e.g.
    "_chunk_runs", the training loop's chunk program: one trace per compiled program)."""
    counter = [0]

    def listener(event, duration, **kwargs):
        if event == _TRACE_EVENT and kwargs.get("fun_name") == fun_name:
            counter[0] += 1

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield counter
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)
