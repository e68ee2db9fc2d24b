"""-v/-q (and --version) wherever a user types them: before a subcommand or after it.

click binds an option to the command it follows, so a group's ``-q`` typed after the
subcommand (``snail-client localize --input P.json -q``) is "No such option". A
``VerbosityGroup`` gives every subcommand added to it its own ``-v/--verbose`` and
``-q/--quiet`` (same help as the group's) and the group's ``--version``. The subcommand's
flags write into the group's dict (``ctx.obj``), so a command reads one answer, ``flags()``,
wherever they were typed; ``-v`` and ``-q`` together are a usage error either way.

The group's own callback must still set ``ctx.obj = {"verbose": ..., "quiet": ...}``
(snail-client, snail-bench and snail-demo do).
"""

from __future__ import annotations

import click


def flags() -> dict:
    """The -v/-q answer of the running command ({} when a command runs without its group)."""
    return click.get_current_context().find_object(dict) or {}


def _set_flag(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    """A subcommand's -v/-q: set it in the group's dict, refuse both."""
    if not value:
        return
    obj = ctx.find_object(dict)
    if obj is None:
        obj = ctx.ensure_object(dict)
    obj[param.name] = True
    if obj.get("verbose") and obj.get("quiet"):
        raise click.UsageError("-v and -q: choose one", ctx)


class VerbosityGroup(click.Group):
    """A click group whose subcommands all accept the group's -v, -q and --version."""

    def add_command(self, cmd: click.Command, name: str | None = None) -> None:
        super().add_command(cmd, name)
        own = {param.name: param for param in self.params}
        taken = {opt for param in cmd.params for opt in param.opts}
        for flag_name, short in (("verbose", "-v"), ("quiet", "-q")):
            if flag_name in own and short not in taken:
                cmd.params.append(click.Option(
                    [short, f"--{flag_name}"], is_flag=True, expose_value=False,
                    callback=_set_flag, help=getattr(own[flag_name], "help", None)))
        if "version" in own and "--version" not in taken:
            cmd.params.append(own["version"])
