"""pyvf's benchmarks, each a module with `main(argv=None) -> exit status` and a `--quick` mode:

    pyvf bench attention   branching attention: pyvf's kernel, torch SDPA, the dense NumPy reference
    pyvf bench vq          nearest-code lookup: pyvf.vq_nearest, torch, numpy, float64 brute force
    pyvf bench transformer one training step, pyvf against the torch oracle model
    pyvf bench codebook    encode/decode and a training step, pyvf against the torch oracle model
    pyvf bench scaling     attention memory and time against the number of views: pyvf, naive stacked, dense

`pyvf bench <name> [args]` (or `python -m pyvf.bench.<name> [args]`) runs one; `--help` lists its
options. Every benchmark validates its results before it times them. torch is imported only
inside the functions that use it: importing a module here does not import torch.
"""

import os

# numpy's BLAS takes its thread count from these variables once, when numpy loads; `pyvf bench`
# sets them to the benchmark's --threads (pyvf.cli.cmd_bench), so that numpy's GEMM and pyvf's
# layers use the threads that pyvf's kernels and torch are given
BLAS_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def blas_thread_env():
    """{variable: value or None} of BLAS_THREAD_VARS in this process, for a benchmark's report."""
    return {v: os.environ.get(v) for v in BLAS_THREAD_VARS}
