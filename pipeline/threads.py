"""How many threads the numerical libraries may use inside the pipeline's work.

The pipeline's unit of parallelism is the item: ``run.workers`` processes fill the cores. A threaded BLAS
on top of that only oversubscribes them, and numpy's OpenBLAS spins its threads while they wait: in the
trace stage of configs/7scenes.toml (two workers, two cores) BLAS threads cost 12 % of the stage's CPU
seconds (169 -> 150 CPU s with one thread) and no wall time. One thread also keeps a product's rounding
independent of how many cores the machine has.
"""

from __future__ import annotations

import contextlib


def one_blas_thread():
    """Context manager limiting BLAS to one thread (threadpoolctl), or a no-op without threadpoolctl.

    Small products (the physics solver's hundreds of rows, the light fit's columns) spend more on waking
    and synchronising threads than on the arithmetic: on a busy machine a 120 x 60 x 120 product took
    1.9 ms instead of 44 us.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    # the limit reaches only the BLAS libraries loaded when it is set: scipy ships its own OpenBLAS,
    # loaded on scipy.linalg's first import, which may come inside the block
    import scipy.linalg  # noqa: F401

    return threadpool_limits(limits=1, user_api="blas")
