"""One line instead of a traceback when a lerobot CLI is given a bad value for our configs.

lerobot's CLIs parse ``--env.*`` / ``--robot.*`` with draccus, which wraps the ValueError of a
config's ``__post_init__`` in a ParsingError: what the user sees is some 40 lines of draccus
frames with our message in the middle. ``config_errors`` tags such an error with the flag group
it belongs to, and ``one_line_errors`` (installed by the plugins when a ``lerobot-*`` command or
``python -m lerobot.<module>`` imports them) prints a tagged error as ``lerobot-eval: error:
--env.type=so101_pick_place: <message>``. Every other exception, and any use outside lerobot's
commands, keeps Python's own report. Imports nothing heavy.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import TracebackType

TAG = "so101_sim_flags"  # attribute set on a tagged exception: the flag group, e.g. --env.type=X
REPORTED = "so101_sim_reported"  # set on a tagged exception once its line is printed
#: What the plugins add to turn an untagged exception of lerobot's own into the one line that
#: says what to do (None: not theirs to explain).
EXPLAINERS: list[Callable[[BaseException], str | None]] = []


@contextmanager
def config_errors(flags: str,
                  kinds: tuple[type[Exception], ...] = (ValueError,)) -> Iterator[None]:
    """Tag an error of `kinds` raised inside with `flags` (how the user named the config).

    Under a lerobot command (``one_line_errors`` installed) the line is also printed here:
    lerobot's parser catches draccus's error for an optional config (lerobot-train's ``env``)
    and prints only "Couldn't instantiate class ..." before it exits, so the hook never sees
    it. The hook then prints nothing more for it."""
    try:
        yield
    except kinds as exc:
        setattr(exc, TAG, flags)
        prog = getattr(sys.excepthook, TAG, None)
        if isinstance(prog, str) and not getattr(exc, REPORTED, False):
            print(f"{prog}: error: {flags}: {exc}", file=sys.stderr)
            setattr(exc, REPORTED, True)
        raise


def say(logger_name: str, level: int, text: str) -> None:
    """Log `text`; straight to stderr while logging is not set up for it: lerobot-train and
    lerobot-rollout parse their command line (building our configs) before they configure
    logging, which would drop an INFO line."""
    logger = logging.getLogger(logger_name)
    if logger.hasHandlers() and logger.isEnabledFor(logging.INFO):  # lerobot's init_logging
        logger.log(level, text)
    else:
        print(f"{logging.getLevelName(level)} {text}", file=sys.stderr)


def causes(exc: BaseException | None) -> Iterator[BaseException]:
    """`exc`, then what it was raised from or during, in turn (a cycle ends the walk)."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        yield exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__


def tagged(exc: BaseException | None) -> BaseException | None:
    """The first tagged exception in `exc`'s chain of causes, or None."""
    return next((e for e in causes(exc) if getattr(e, TAG, None)), None)


def add_explainer(explain: Callable[[BaseException], str | None]) -> None:
    """Add `explain` to ``EXPLAINERS`` once (each plugin that needs it asks)."""
    if explain not in EXPLAINERS:
        EXPLAINERS.append(explain)


def command_name(argv0: str) -> str | None:
    """The lerobot command `argv0` runs (``lerobot-eval``, or the module of ``python -m
    lerobot.async_inference.robot_client``, whose argv[0] is the module's file), else None."""
    path = Path(argv0)
    parts = path.parent.parts
    if path.suffix == ".py" and "lerobot" in parts:
        top = len(parts) - 1 - parts[::-1].index("lerobot")
        return ".".join((*parts[top:], path.stem))
    return path.name if path.name.startswith("lerobot") else None


def one_line_errors(argv0: str | None = None) -> bool:
    """Under a ``lerobot-*`` command, report a tagged config error in one line; returns whether
    the hook is in place. Installed once; other exceptions go to the hook that was there."""
    prog = command_name(argv0 if argv0 is not None else (sys.argv[0] if sys.argv else ""))
    if prog is None:
        return False
    if getattr(sys.excepthook, TAG, False):
        return True
    previous = sys.excepthook

    def hook(kind: type[BaseException], exc: BaseException,
             tb: TracebackType | None) -> None:
        ours = tagged(exc)
        if ours is not None:
            if not getattr(ours, REPORTED, False):
                print(f"{prog}: error: {getattr(ours, TAG)}: {ours}", file=sys.stderr)
            return
        line = next((said for explain in EXPLAINERS if (said := explain(exc))), None)
        if line is None:
            previous(kind, exc, tb)
            return
        print(f"{prog}: error: {line}", file=sys.stderr)

    setattr(hook, TAG, prog)  # the command's name, for config_errors
    sys.excepthook = hook
    return True
