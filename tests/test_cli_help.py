"""
The command lines' ``--help`` is plain text with the command a user types in its usage line. Before, it showed the
module docstrings' reStructuredText (double backticks, ``:mod:`` roles), and ``usage: plotting.py``.
"""

import pytest

import sb3_lifelong.buffers.__main__ as buffers_cli
import sb3_lifelong.experiments.__main__ as experiments_cli
import sb3_lifelong.zoo.__main__ as zoo_cli
from sb3_lifelong.core.cli import plain_text

#: reStructuredText markup that a terminal shows as it is
MARKUP = ("``", ":mod:", ":class:", ":func:", ":meth:", ":data:", "::")

#: each command line: its main function, the command a user types, and a subcommand's arguments
COMMANDS = [
    pytest.param(experiments_cli.main, "python -m sb3_lifelong.experiments", ["run"], id="experiments"),
    pytest.param(buffers_cli.main, "python -m sb3_lifelong.buffers", ["verify"], id="buffers"),
]


def help_of(main, argv: list[str], capsys) -> str:
    """:return: what ``main(argv + ["--help"])`` prints (argparse exits with status 0 after it)"""
    with pytest.raises(SystemExit) as exited:
        main([*argv, "--help"])
    assert exited.value.code == 0
    return capsys.readouterr().out


def assert_plain(text: str) -> None:
    found = [markup for markup in MARKUP if markup in text]
    assert not found, f"reStructuredText {found} in:\n{text}"


@pytest.mark.parametrize("main, command, subcommand", COMMANDS)
def test_help_is_plain_text_with_the_command_in_its_usage(main, command, subcommand, capsys):
    text = help_of(main, [], capsys)
    assert text.startswith(f"usage: {command} [-h]")
    assert_plain(text)
    if subcommand:
        text = help_of(main, subcommand, capsys)
        assert text.startswith(f"usage: {command} {subcommand[0]} [-h]")
        assert_plain(text)


def test_the_descriptions_keep_their_words_and_examples(capsys):
    text = help_of(experiments_cli.main, [], capsys)
    assert "(and its three-stage variant: a study's own presets, --presets\nbenchmarks/" in text
    assert "Run one seed (every job of it that has not finished yet):\n\n    python -m sb3_lifelong.experiments run" in text


def test_the_zoo_help_is_plain_text(capsys):
    zoo_cli.main(["--help"])
    text = capsys.readouterr().out
    assert text.startswith("usage: python -m sb3_lifelong.zoo {train,enjoy,")
    assert_plain(text)


@pytest.mark.parametrize(
    "rst, plain",
    [
        ("``python -m x``: the figures", "python -m x: the figures"),
        ("see :mod:`sb3_lifelong.experiments.plots`", "see sb3_lifelong.experiments.plots"),
        ("a :class:`~sb3_lifelong.envs.DynamicsSchedule` and :py:func:`f`", "a DynamicsSchedule and f"),
        (":doc:`the install guide <guide/install>`", "the install guide"),
        (
            "`Gymnasium <https://gymnasium.farama.org>`_ and `interpreted`",
            "Gymnasium (https://gymnasium.farama.org) and interpreted",
        ),
        ("a ``literal that\nspans`` two lines, **strong**", "a literal that\nspans two lines, strong"),
        ("Usage::\n\n    python -m x", "Usage:\n\n    python -m x"),
        ("An example ::\n\n    code", "An example\n\n    code"),
        ("Text.\n\n::\n\n    code", "Text.\n\n    code"),
        ("\n    indented docstring, ``x`` *args and *.csv\n    ", "indented docstring, x *args and *.csv"),
    ],
)
def test_plain_text_drops_the_markup(rst, plain):
    assert plain_text(rst) == plain
