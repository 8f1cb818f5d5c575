"""``mitsuba-active view``: a run in the browser, on viser."""

from __future__ import annotations

import click

from ..viewer import serve
from .common import Command, one_line_errors


@click.command(cls=Command)
@click.argument("run_dir", type=click.Path())
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to serve on (0.0.0.0: every one).")
@click.option("--port", type=int, default=8080, show_default=True,
              help="Port to serve on (the next free one if taken).")
@click.option("--follow", is_flag=True, help="Redraw as a plan writes the folder.")
@one_line_errors(libraries=False)
def view(run_dir, host, port, follow):
    """Show a run in the browser: its cameras, each round's scores, its captures.

    Clicking a camera renders the planner's ensemble's mean and variance from it. Needs
    the viewer extra: pip install 'mitsuba-active[viewer]'.
    """
    serve(run_dir, host, port, follow, log=lambda m: click.echo(m, err=True))

