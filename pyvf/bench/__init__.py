"""pyvf's benchmarks, each a module with `run(...) -> report` (a dict, JSON-able) and a quick mode:

    pyvf bench attention   branching attention: pyvf's kernel, torch SDPA, the dense NumPy reference
    pyvf bench vq          nearest-code lookup: pyvf.vq_nearest, torch, numpy, float64 brute force
    pyvf bench transformer one training step, pyvf against the torch oracle model
    pyvf bench codebook    one training step, pyvf against the torch oracle model
    pyvf bench scaling     attention memory and time against the number of views: pyvf, naive stacked, dense
    pyvf bench accuracy    speed against error: every op and variant against a float64 reference
    pyvf bench hardcases   sweeps into the hard cases, pyvf's stated bound checked along each
    pyvf bench report      docs/performance.md and docs/accuracy.md from the three above

`pyvf bench <name> [args]` runs one (its options: `pyvf bench <name> --help`, parsed in
pyvf/cli/bench.py, which calls the module's run()); common.py holds what they share (time and
memory measured, tables, JSON). Every benchmark validates its results before it times them.
torch is imported only inside the functions that use it: importing a module here does not
import torch.
"""

from .common import BLAS_THREAD_VARS

__all__ = ["BLAS_THREAD_VARS"]
