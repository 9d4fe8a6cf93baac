"""The science core: channel model, fingerprints, measurements, solvers, simulation.

numpy/scipy, cvxpy for l1 and numba for the hot kernels; no web or database imports (a test
enforces this).
"""
