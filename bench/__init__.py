"""The benchmark harness (``cloudgraph bench``, docs/benchmark.md) and its one-question scripts."""
