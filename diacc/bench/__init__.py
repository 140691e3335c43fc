"""Benchmarks behind ``diacc bench``: each module measures side by side in one run."""
