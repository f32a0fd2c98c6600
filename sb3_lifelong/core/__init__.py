"""
The bottom layer: what the environments, the buffer and the algorithms agree on, importing nothing of the package.

- :mod:`~sb3_lifelong.core.contract`: the ``info`` keys the environments write and the buffer reads, and the hook
  through which an algorithm tells an environment its timestep;
- :mod:`~sb3_lifelong.core.datasets`: d4rl dicts, ``.npz`` files and Minari datasets: reading, the one validator, the
  one action normaliser;
- :mod:`~sb3_lifelong.core.safe_load`: what a saved model's pickled parts may contain (``load(..., safe=True)``).
"""
