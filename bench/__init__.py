"""The benchmarks, one package: ``python -m bench.<name>`` from the repository root; shared helpers in bench.common."""
