"""``hydo``: the typer app. One module per command; this file only composes them and maps known
errors to one stderr line and a non-zero exit (set ``HYDO_DEBUG=1`` for the full traceback)."""

from __future__ import annotations

import errno
import os
import signal
import sys

import typer

from hydo_cli import deploy, evaluate, export, plot, review, sweep, train

app = typer.Typer(
    name="hydo",
    help="Train, evaluate, export and deploy HyDo policies (Hybrid Diffusion Policy) for "
    "non-prehensile manipulation: push and flip an object in a bin to a goal 6D pose.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)
app.command("train", help=train.HELP)(train.train)
app.command("eval", help=evaluate.HELP)(evaluate.evaluate)
app.command("export", help=export.HELP)(export.export)
# `hydo deploy review SESSION`: beside capture-background / capture-goal (the deploy callback returns
# at once when a subcommand is named, so `hydo deploy --robot sim ...` is unchanged)
deploy.app.command("review", help=review.HELP)(review.review)
app.add_typer(deploy.app, name="deploy")
app.command("plot", help=plot.HELP)(plot.plot)
app.command("sweep", help=sweep.HELP)(sweep.sweep)


#: errno values of a write the user's disk refused (permissions, read-only, full, quota).
USER_OS_ERRORS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT}


def main() -> None:
    from hydo_cli.errors import known_errors

    known = known_errors()

    def on_sigterm(signum, frame):  # SIGTERM is Ctrl-C: each command cleans up, typer exits 130
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_sigterm)
    try:
        app()  # standalone: click handles usage errors (exit 2), --help and typer.Exit itself
    except known as e:  # one clear line, never a traceback, for user-facing failures
        if os.environ.get("HYDO_DEBUG"):
            raise
        typer.secho(f"hydo: error: {e}", err=True, fg=typer.colors.RED)
        sys.exit(1)
    except OSError as e:
        # A folder that turned read-only or full between a command's own checks and its write is the
        # machine's state, not a bug: one line naming the path. Any other OSError keeps its traceback.
        if e.errno not in USER_OS_ERRORS or os.environ.get("HYDO_DEBUG"):
            raise
        where = f"{e.filename}: " if e.filename else ""
        typer.secho(f"hydo: error: cannot write {where}{e.strerror}", err=True, fg=typer.colors.RED)
        sys.exit(1)


if __name__ == "__main__":
    main()
