"""pyvf's benchmarks: each module's run(quick, threads, ...) validates, then times, prints its tables
and returns its report (a JSON-able dict, its failures listed); `pyvf bench NAME` calls it."""
