"""The default solver's compiled (numba) kernels; each computes the same numbers as the NumPy
code it stands in for (``tests/vlp/gridless/test_compiled.py``). Private: callers validate."""
