"""`so101-sim` command line: ``main`` parses (``parser``) and runs a command (``commands``)."""

from __future__ import annotations

import sys

from so101_sim.cli.parser import build_parser, parse_camera_map_arg, parse_image_size

__all__ = ["build_parser", "main", "parse_camera_map_arg", "parse_image_size"]


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except PermissionError as exc:
        print(f"so101-sim {args.command}: error: cannot write or read {exc.filename}: "
              "permission denied; choose a folder you own (e.g. under your home) for --out",
              file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"so101-sim {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
