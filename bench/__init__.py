"""The benchmarks: python -m bench.<name> (or python bench/<name>.py); shared helpers in bench.common."""
