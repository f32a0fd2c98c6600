"""
``python -m sb3_lifelong.zoo {train,enjoy} --algo mpo ...``: rl-zoo3's commands with this package's algorithms.

Every argument after the command is rl-zoo3's own (``python -m rl_zoo3.train --help``). Without ``--conf-file`` /
``-conf``, an algorithm of this package uses this package's hyperparameter file (``sb3_lifelong/zoo/hyperparams``).
"""

import sys
from typing import Optional

from sb3_lifelong.zoo import ALGORITHMS, hyperparams_file, register

COMMANDS = ("train", "enjoy")


def main(argv: Optional[list[str]] = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] not in COMMANDS:
        print(__doc__)
        raise SystemExit(f"usage: python -m sb3_lifelong.zoo {{{','.join(COMMANDS)}}} --algo mpo --env Hopper-v5 ...")
    command, rest = args[0], args[1:]
    register()
    algo = next((rest[i + 1] for i, arg in enumerate(rest[:-1]) if arg == "--algo"), None)
    if command == "train" and algo in ALGORITHMS and not {"--conf-file", "-conf"} & set(rest):
        rest += ["--conf-file", str(hyperparams_file(algo))]
    sys.argv = [f"rl_zoo3.{command}", *rest]
    if command == "train":
        from rl_zoo3.train import train

        train()
    else:
        from rl_zoo3.enjoy import enjoy

        enjoy()


if __name__ == "__main__":
    main()
