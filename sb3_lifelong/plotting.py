"""
``python -m sb3_lifelong.plotting <dir>``: the figures of an experiment of ``examples/`` (PNG, in ``<dir>``).

The code is :mod:`sb3_lifelong.experiments.plots`; this module is its command line.
"""

from sb3_lifelong.experiments.plots import load_experiment, main, plot_experiment

__all__ = ["load_experiment", "main", "plot_experiment"]

if __name__ == "__main__":
    main()
