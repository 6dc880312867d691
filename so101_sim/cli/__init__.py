"""`so101-sim` command line: ``main`` parses (``parser``) and runs a command (``commands``)."""

from __future__ import annotations

import sys

from so101_sim.cli.arg_types import parse_camera_map_arg, parse_image_size
from so101_sim.cli.parser import build_parser, parse_command_line
from so101_sim.utils.collector import freeze_for_exit, own_process
from so101_sim.utils.disk import again_hint, free_space, is_disk_full, set_command
from so101_sim.utils.environ import environ_set
from so101_sim.workers.ray_connect import CONNECT_TIMEOUT_ENV, signal_exit_code

__all__ = ["build_parser", "main", "parse_camera_map_arg", "parse_image_size"]


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # the process is this command (the entry point), not a caller's call
        own_process()
    args = parse_command_line(argv)
    timeout = getattr(args, "ray_connect_timeout", None)  # read by workers.ray_connect
    if timeout is not None and args.ray_address is None:
        print(f"so101-sim {args.command}: error: --ray-connect-timeout "
              f"{timeout:g} only applies with --ray-address (the seconds "
              "to wait for that cluster); add --backend ray --ray-address ADDR, or drop "
              "--ray-connect-timeout", file=sys.stderr)
        return 2
    # What this command sets for the code it runs lasts as long as the command: a caller
    # that goes on in the same process (main() from Python, then the API) gets neither this
    # command line in its disk-full hints nor its Ray connect timeout.
    scoped = {} if timeout is None else {CONNECT_TIMEOUT_ENV: str(timeout)}
    set_command(["so101-sim", *(sys.argv[1:] if argv is None else argv)])  # disk-full hint
    try:
        # SIGTERM exits 15 wherever in Ray it lands
        with environ_set(scoped), signal_exit_code():
            return args.func(args)
    except KeyboardInterrupt:  # Ctrl-C while a command starts (imports, loading): one line
        print(f"so101-sim {args.command}: interrupted", file=sys.stderr)
        return 130
    except PermissionError as exc:
        print(f"so101-sim {args.command}: error: cannot write or read {exc.filename}: "
              "permission denied; choose a folder you own (e.g. under your home) for --out",
              file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"so101-sim {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk outside a locked folder: one line too
        if not is_disk_full(exc):
            raise
        print(f"so101-sim {args.command}: error: the disk is full ({exc.filename or exc}): "
              f"{free_space(exc.filename or '.')} free there; {again_hint('rerun')}",
              file=sys.stderr)
        return 2
    finally:
        set_command(None)
        freeze_for_exit()  # the interpreter's teardown then skips torch's objects


if __name__ == "__main__":
    sys.exit(main())
