"""The science core: channel model, fingerprints, measurements, solvers, simulation.

Pure numpy/scipy/cvxpy; no web or database imports (a test enforces this).
"""
