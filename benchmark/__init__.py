"""The benchmark runner: composes scenes, integrators and diagnostics into sweeps, tables and plots.

    python -m benchmark run            # the default sweep of the paper's three scenes -> results/
    python -m benchmark run --quick    # a reduced sweep, a few minutes on 2 cores
"""
