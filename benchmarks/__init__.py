"""The benchmark scripts, importable (``benchmarks.part_retrieval``) so that tests can check their scoring; each
is run as ``python benchmarks/<name>.py`` and prints its figures beside its peers."""
