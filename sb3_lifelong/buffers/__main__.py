"""
``python -m sb3_lifelong.buffers verify PATH``: check every chunk of a buffer directory (exit status 0: intact, 1: some
chunks are damaged, 2: no buffer there or its manifest is not valid).

``python -m sb3_lifelong.buffers salvage PATH NEW``: copy the intact chunks of a buffer directory into a new one (exit
status 0: every transition copied, 1: those of damaged chunks left out, 2: nothing copied). ``PATH`` is never written.
"""

from __future__ import annotations

import argparse
import sys
from typing import Optional

from sb3_lifelong.buffers.manifest import BufferFormatError
from sb3_lifelong.buffers.salvage import check_buffer, salvage_buffer


def main(argv: Optional[list[str]] = None) -> int:
    """:param argv: the arguments (default: the command line's). :return: the exit status"""
    parser = argparse.ArgumentParser(prog="python -m sb3_lifelong.buffers", description=__doc__.split("\n\n")[0].strip())
    commands = parser.add_subparsers(dest="command", required=True)
    verify = commands.add_parser("verify", help="check every chunk's files and checksums (reads the whole buffer)")
    verify.add_argument("path", help="the buffer directory (only read)")
    salvage = commands.add_parser("salvage", help="copy the intact chunks into a new buffer directory")
    salvage.add_argument("path", help="the damaged buffer directory (only read)")
    salvage.add_argument("destination", help="a new (or empty) directory for the copy")
    salvage.add_argument("--chunk-size", type=int, default=10_000, help="transitions per chunk of the copy")
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
