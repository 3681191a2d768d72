"""Applications: the command line, the demo, the benchmarks, studies and the paper's figures."""
