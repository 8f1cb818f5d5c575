"""The ``mitsuba-active`` command line: one module per command, loaded when that command runs.

A command's module imports the libraries it needs, so ``mitsuba-active view``
starts without the field, the planners or the benchmark runner.
Every command turns bad input (:class:`~mitsuba_active.errors.UserError`)
and files it cannot read or write (``OSError``) into one line on stderr and
exit code 2 (:func:`.common.one_line_errors`).
"""

from __future__ import annotations

import importlib

from ..checks import nearest
from ..interrupts import interruptible_imports

with interruptible_imports():  # click loads here, after the package's own imports
    import click

    from .common import exit_interrupted

#: The commands, each the function of the same name in the module of the same name.
COMMANDS = ("bench", "export", "plan", "render", "scene", "view")


class _Commands(click.Group):
    """The group of :data:`COMMANDS`, each imported when it is asked for."""

    def list_commands(self, ctx) -> list[str]:
        return sorted(set(COMMANDS) | set(self.commands))

    def resolve_command(self, ctx, args):
        name = args[0] if args else None
        if name is not None and name not in COMMANDS and name not in self.commands:
            near = nearest(name, COMMANDS)  # the group's own commands are not loaded to be compared
            ctx.fail(f"No such command {name!r}." + (f" Did you mean {near!r}?" if near else ""))
        return super().resolve_command(ctx, args)

    def get_command(self, ctx, name: str):
        if name not in COMMANDS:
            return super().get_command(ctx, name)
        try:
            # Ctrl-C is held back while the command's libraries load (see .interrupts), then ends it.
            with interruptible_imports():
                module = importlib.import_module(f".{name}", __name__)
        except KeyboardInterrupt:
            exit_interrupted()
        return getattr(module, name)


@click.group(cls=_Commands, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mitsuba-active")
def main():
    """Active view planning of radiance fields with Mitsuba 3 and Dr.Jit."""

