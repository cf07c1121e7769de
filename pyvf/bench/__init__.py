"""pyvf's benchmarks, each a module with `main(argv=None) -> exit status` and a `--quick` mode:

    pyvf bench attention   branching attention: pyvf's kernel, torch SDPA, the dense NumPy reference
    pyvf bench vq          nearest-code lookup: pyvf.vq_nearest, torch, numpy, float64 brute force
    pyvf bench transformer one training step, pyvf against the torch oracle model
    pyvf bench codebook    encode/decode and a training step, pyvf against the torch oracle model

`pyvf bench <name> [args]` (or `python -m pyvf.bench.<name> [args]`) runs one; `--help` lists its
options. Every benchmark validates its results before it times them. torch is imported only
inside the functions that use it: importing a module here does not import torch.
"""
