"""pyvf's benchmarks, each a module whose run(quick, threads, ...) prints its tables and returns its
report (a JSON-able dict with a list of failures), called by `pyvf bench NAME` (pyvf/cli/bench.py).
Each validates its results before it times them. torch is imported only where it is used.
"""
