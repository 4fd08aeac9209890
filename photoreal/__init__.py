"""photoreal, the application: the command line (``cli``), the demo report (``demo``) and the benchmarks."""
