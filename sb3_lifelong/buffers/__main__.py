"""
``python -m sb3_lifelong.buffers verify PATH``: check every chunk of a buffer directory (exit status 0: intact, 1: some
chunks are damaged, 2: no buffer there or its manifest is not valid).

``python -m sb3_lifelong.buffers salvage PATH NEW``: copy the intact chunks of a buffer directory into a new one (exit
status 0: every transition copied, 1: those of damaged chunks left out, 2: nothing copied, e.g. a usage error such as
``--chunk-size 0``, or ``NEW`` that is not a new or empty directory outside ``PATH``). ``PATH`` is never written.
"""

from __future__ import annotations

import argparse
import sys
from typing import Optional

from sb3_lifelong.buffers.manifest import BufferFormatError
from sb3_lifelong.buffers.salvage import check_buffer, salvage_buffer
from sb3_lifelong.core.cli import plain_text


def positive_int(text: str) -> int:
    """
    :param text: A command-line value
    :return: It, as a positive int
    :raises argparse.ArgumentTypeError: otherwise (argparse reports it as a usage error, exit status 2)
    """
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive int, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive int (transitions per chunk), got {value}")
    return value


def main(argv: Optional[list[str]] = None) -> int:
    """:param argv: the arguments (default: the command line's). :return: the exit status"""
    parser = argparse.ArgumentParser(
        prog="python -m sb3_lifelong.buffers", description=plain_text(__doc__.split("\n\n")[0].strip())
    )
    commands = parser.add_subparsers(dest="command", required=True)
    verify = commands.add_parser("verify", help="check every chunk's files and checksums (reads the whole buffer)")
    verify.add_argument("path", help="the buffer directory (only read)")
    salvage = commands.add_parser("salvage", help="copy the intact chunks into a new buffer directory")
    salvage.add_argument("path", help="the damaged buffer directory (only read)")
    salvage.add_argument("destination", help="a new (or empty) directory for the copy")
    salvage.add_argument("--chunk-size", type=positive_int, default=10_000, help="transitions per chunk of the copy")
    args = parser.parse_args(argv)
    try:
        if args.command == "verify":
            report = check_buffer(args.path)
        else:
            report = salvage_buffer(args.path, args.destination, chunk_size=args.chunk_size)
    except (BufferFormatError, FileNotFoundError, FileExistsError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(report.summary())
    return 1 if report.damaged else 0


if __name__ == "__main__":
    sys.exit(main())
