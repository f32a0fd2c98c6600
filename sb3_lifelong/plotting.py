"""
The figures of an experiment in the sequential layout of the package's earlier examples (the committed
``benchmarks/studies/two_stage_quick`` and ``two_stage_50k``), in the package's one style
(:mod:`sb3_lifelong.experiments.style`: the methods the examples share with the studies have the studies' names and
colours, e.g. ``distilled`` is "CRR exp β=1", red, as in every figure). The examples (``examples/three_stage.py``,
``continuous_drift.py``, ``parallel_sharing.py``) write a study of the protocol instead, whose figures
``python -m sb3_lifelong.experiments report <dir>`` draws.

Reads the layout the examples write (``<dir>/seed_<k>/<method>/eval.csv`` and ``q_sources.csv``,
``<dir>/seed_<k>/stages.json``) and writes into ``<dir>``:

- ``curves_<env>.png``: evaluation return in each environment against environment steps, for the online methods
  (mean over seeds, +- std band with two seeds or more), the environment changes as labelled vertical lines and the
  distilled policies' final return as dotted horizontal lines;
- ``final_returns.png``: the final return of every method in every environment (mean +- std over seeds);
- ``q_sources.png``: each online method's average Q-value on each environment's data (the overestimation curves),
  one line per seed (and from three seeds on their median and interquartile range, which no diverging seed drags);
- ``distillation.png``: the distilled policies' return against offline updates, one panel per environment.

The methods are read from the directory: the distilled ones are those named in ``stages.json`` (outputs written
before it named them: the methods whose name starts with ``distilled``), the online ones all the others. A method
keeps its name and colour in every figure. Usage::

    python -m sb3_lifelong.plotting benchmarks/studies/two_stage_quick
"""

# this module is the command line (its docstring is the help); the figures' code is sb3_lifelong.experiments.figures

import argparse
from typing import Optional

from sb3_lifelong.core.cli import plain_text
from sb3_lifelong.experiments.figures import load_experiment, plot_experiment

__all__ = ["load_experiment", "main", "plot_experiment"]


def main(argv: Optional[list[str]] = None) -> None:
    """
    The command line: ``python -m sb3_lifelong.plotting <dir>``.

    :param argv: the arguments (default: ``sys.argv[1:]``)
    """
    parser = argparse.ArgumentParser(
        prog="python -m sb3_lifelong.plotting",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("directory", help="an experiment's output directory")
    args = parser.parse_args(argv)
    for path in plot_experiment(args.directory):
        print("wrote", path)


if __name__ == "__main__":
    main()
