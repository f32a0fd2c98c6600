"""
``python -m sb3_lifelong.zoo COMMAND [rl-zoo3's arguments]``: rl-zoo3's commands with this package's algorithms.

Commands: ``train``, ``enjoy``, ``record-video`` (rl-zoo3's ``record_video``), ``plot-train``, ``plot-from-file``,
``all-plots``. Every argument after the command is rl-zoo3's own (``python -m sb3_lifelong.zoo train --help``).
Without ``--conf-file`` / ``-conf``, ``train`` with an algorithm of this package uses this package's hyperparameter
file (``sb3_lifelong/zoo/hyperparams``). A hyperparameter file may name this package's classes
(``replay_buffer_class: sb3_lifelong.LifelongReplayBuffer``), and ``-optimize`` searches MPO's and CRR's spaces.
"""

import runpy
import sys
from collections.abc import Callable
from typing import Any, Optional

from sb3_lifelong.zoo import ALGORITHMS, hyperparams_file, register


def _train() -> None:
    from rl_zoo3.train import train

    train()


def _enjoy() -> None:
    from rl_zoo3.enjoy import enjoy

    enjoy()


def _record_video() -> None:
    runpy.run_module("rl_zoo3.record_video", run_name="__main__")  # a script, not a function, in rl-zoo3


def _plots() -> Any:
    """:return: rl-zoo3's plots module (its plots need packages that rl-zoo3 itself does not install)"""
    try:
        from rl_zoo3 import plots
    except ModuleNotFoundError as error:
        raise ImportError(
            f"rl-zoo3's plot commands need {error.name!r}, which is not installed: pip install 'rl_zoo3[plots]'"
        ) from error
    return plots


def _plot_train() -> None:
    _plots().plot_train()


def _plot_from_file() -> None:
    _plots().plot_from_file()


def _all_plots() -> None:
    _plots().all_plots()


#: the commands, by name, and the rl-zoo3 entry point each runs
COMMANDS: dict[str, Callable[[], None]] = {
    "train": _train,
    "enjoy": _enjoy,
    "record-video": _record_video,
    "plot-train": _plot_train,
    "plot-from-file": _plot_from_file,
    "all-plots": _all_plots,
}
USAGE = f"usage: python -m sb3_lifelong.zoo {{{','.join(COMMANDS)}}} --algo mpo --env Hopper-v5 ..."
#: what ``--help`` prints: plain text for a terminal (the module's docstring is reStructuredText, for the docs)
HELP = f"""{USAGE}

rl-zoo3's commands, with this package's algorithms (--algo mpo, --algo crr) registered.

commands:
  train           train an agent
  enjoy           run a trained agent
  record-video    record a video of a trained agent (rl-zoo3's record_video)
  plot-train      plot a training run
  plot-from-file  plot results saved by all-plots
  all-plots       plot the results of several runs

Every argument after the command is rl-zoo3's own: python -m sb3_lifelong.zoo train --help lists them.
Without --conf-file (-conf), train with MPO or CRR uses this package's hyperparameter file
(sb3_lifelong/zoo/hyperparams). A hyperparameter file may name this package's classes
(replay_buffer_class: sb3_lifelong.LifelongReplayBuffer), and -optimize searches MPO's and CRR's
hyperparameter spaces.

example: python -m sb3_lifelong.zoo train --algo mpo --env Hopper-v5 -n 100000"""


def main(argv: Optional[list[str]] = None) -> None:
    """
    Run one of rl-zoo3's commands with this package registered.

    :param argv: the command and its arguments (default: ``sys.argv[1:]``)
    :raises SystemExit: with the usage, for no command or an unknown one (``--help`` prints it and returns)
    """
    args = list(sys.argv[1:] if argv is None else argv)
    if args and args[0] in ("-h", "--help"):
        print(HELP)
        return
    if not args or args[0] not in COMMANDS:
        print(HELP)
        given = f"unknown command {args[0]!r}; " if args else ""
        raise SystemExit(f"{given}{USAGE}")
    command, rest = args[0], args[1:]
    register()
    algo = next((rest[i + 1] for i, arg in enumerate(rest[:-1]) if arg == "--algo"), None)
    if command == "train" and algo in ALGORITHMS and not {"--conf-file", "-conf"} & set(rest):
        rest += ["--conf-file", str(hyperparams_file(algo))]
    sys.argv = [f"rl_zoo3.{command}", *rest]
    COMMANDS[command]()


if __name__ == "__main__":
    main()
