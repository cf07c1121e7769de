"""pyvf's benchmarks: attention, vq, steps (transformer and codebook), scaling, accuracy, hardcases,
report, each a module whose run() returns its report (a dict, JSON-able), called by `pyvf bench
NAME` (pyvf/cli/bench.py); common.py holds what they share. Every benchmark validates its results
before it times them, on the threads it is given: pyvf's kernels and numpy's BLAS pool together
(pyvf.set_num_threads), and torch's. torch is imported only inside the functions that use it.
"""
