"""``mitsuba-active export``: a run's views as a transforms.json dataset."""

from __future__ import annotations

import click

from ..export import export_transforms
from .common import Command, one_line_errors


@click.command(cls=Command)
@click.argument("run_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "out", type=click.Path(file_okay=False), default=None,
              help="Dataset folder [RUN_DIR/export].")
@one_line_errors
def export(run_dir, out):
    """Export a run's chosen and held-out views as a transforms.json dataset.

    The dataset reads in nerfstudio and instant-ngp, split as the run was.
    """
    click.echo(f"wrote {export_transforms(run_dir, out)}")

