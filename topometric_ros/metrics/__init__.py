"""Map-consistency metrics over a window of scans (pure numpy/scipy, no I/O): PNE, CPV and baselines."""
