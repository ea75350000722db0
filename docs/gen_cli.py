"""The command reference, generated from the click command line (``ari_sfm.cli:main``), never hand-copied.

``command_pages()`` gives one Markdown page per command (``cli/<command>.md``, a subcommand of a group as
``cli/<group>-<command>.md``) and the index ``cli/index.md``: each command's usage, its help text and a table
of its arguments and options (flags, type, default, help) as ``ari-sfm COMMAND --help`` prints them. The
docs build calls it from ``docs/hooks.py``; ``python docs/gen_cli.py OUT`` writes the pages into a folder.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import click


@dataclass(frozen=True)
class CommandPage:
    """One generated page: the command's words (``("import", "openptv")``), its file and its Markdown."""

    words: tuple[str, ...]
    path: str
    markdown: str
    summary: str

    @property
    def title(self) -> str:
        return " ".join(self.words)


def _commands(group: click.Group, ctx: click.Context, words: tuple[str, ...] = ()):
    """Every (words, command, context) below ``group``, subgroups' commands included, in name order."""
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        if cmd is None or cmd.hidden:
            continue
        sub = click.Context(cmd, info_name=name, parent=ctx)
        yield (*words, name), cmd, sub
        if isinstance(cmd, click.Group):
            yield from _commands(cmd, sub, (*words, name))


def _cell(text: str) -> str:
    """Text fit for one cell of a Markdown table."""
    return " ".join(str(text).split()).replace("|", "\\|")


def _default(param: click.Parameter, ctx: click.Context) -> str:
    if isinstance(param, click.Option) and param.is_flag and not param.secondary_opts:
        return "off" if not param.default else "on"
    value = param.get_default(ctx, call=True)
    if param.required or value is getattr(click.core, "UNSET", object()) or value is None or value == () or value == "":
        return ""
    if isinstance(value, bool) and param.secondary_opts:
        return param.opts[0] if value else param.secondary_opts[0]
    if isinstance(value, (tuple, list)):
        return " ".join(map(str, value))
    return str(value)


def _params_table(cmd: click.Command, ctx: click.Context) -> list[str]:
    rows = ["`-h`, `--help` prints this page's text.", "", "| argument or option | takes | default | what it is |",
            "|---|---|---|---|"]
    for p in cmd.get_params(ctx):
        if getattr(p, "hidden", False) or p.name == "help":
            continue
        if isinstance(p, click.Argument):
            name, takes = f"`{p.human_readable_name}`", p.type.name
            help_text = "required" if p.required else "optional"
        else:
            name = ", ".join(f"`{o}`" for o in (*p.opts, *p.secondary_opts))
            takes = "flag" if p.is_flag else (p.metavar or p.make_metavar(ctx))
            help_text = (p.help or "") + (" (required)" if p.required else "")
        rows.append(f"| {name} | {_cell(takes)} | {_cell(_default(p, ctx))} | {_cell(help_text)} |")
    return rows


def command_pages(root: click.Group | None = None) -> list[CommandPage]:
    """The pages of every command of ``root`` (default: ``ari_sfm.cli.main``), in name order."""
    if root is None:
        from ari_sfm.cli import main as root
    top = click.Context(root, info_name="ari-sfm")
    pages = []
    for words, cmd, ctx in _commands(root, top):
        full = "ari-sfm " + " ".join(words)
        help_text = (cmd.help or "").strip()
        summary = cmd.get_short_help_str(limit=120)
        usage = " ".join(cmd.collect_usage_pieces(ctx))
        lines = [f"# {full}", "", f"<!-- generated from `{full} --help` by docs/gen_cli.py: do not edit -->", "",
                 "```text", f"Usage: {full} {usage}", "```", ""]
        lines += ["\n\n".join(" ".join(par.split()) for par in help_text.replace("\b\n", "").split("\n\n")), ""]
        if isinstance(cmd, click.Group):
            lines += ["| command | what it does |", "|---|---|"]
            for name in cmd.list_commands(ctx):
                sub = cmd.get_command(ctx, name)
                lines.append(f"| [`{full} {name}`]({'-'.join((*words, name))}.md) | "
                             f"{_cell(sub.get_short_help_str(limit=120))} |")
        else:
            lines += _params_table(cmd, ctx)
        lines += ["", "The same text: `" + full + " --help`."]
        pages.append(CommandPage(words, f"cli/{'-'.join(words)}.md", "\n".join(lines) + "\n", summary))
    index = ["# Command reference", "",
             "<!-- generated from the command line by docs/gen_cli.py: do not edit -->", "",
             "Every command of `ari-sfm` (`python -m ari_sfm COMMAND` runs the same), generated from its "
             "`--help`. `ari-sfm -v COMMAND` logs progress messages; `ari-sfm --version` prints the version. "
             "`calibrate`, `run`, `particles` and `self-calibrate` also read their options from a YAML file "
             "(`--config FILE`, see [the config file](../guide/config.md)).", "",
             "| command | what it does |", "|---|---|"]
    index += [f"| [`ari-sfm {p.title}`]({p.path.removeprefix('cli/')}) | {_cell(p.summary)} |" for p in pages]
    pages.insert(0, CommandPage((), "cli/index.md", "\n".join(index) + "\n", "every command"))
    return pages


def main(out: str) -> None:
    """Write the pages under OUT (``OUT/cli/*.md``)."""
    for page in command_pages():
        path = Path(out) / page.path
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(page.markdown)
        print(path)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "site-cli")
