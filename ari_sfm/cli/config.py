"""``--config FILE``: a command's options from a YAML mapping, command-line options overriding it.

The file is a mapping of option names to values, the names as the command's ``--help`` shows them with or
without their dashes (``huber_px: 0.5`` or ``huber-px: 0.5``; a ``--x/--no-x`` flag is ``x: true`` or
``x: false``; an option of two values a list: ``depth_range: [-20, 20]``). It becomes click's
``default_map`` of the command, so an option given on the command line wins, and each value goes through
the option's own type. An unknown key, an argument (DATASET) or a value of the wrong type is one error
line naming the file and the key; so is a value a command's own checks refuse (``huber_px: -1``) when it
came from the file (:func:`blame_config`).
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import click
from click.core import ParameterSource

from ..errors import AriSfmError
from ..io.structured import as_mapping, read_structured, show

CONFIG_META = "ari_sfm.config"  # ctx.meta key: the config file the command's defaults came from

CONFIG_HELP = ("YAML file of this command's options: option names as keys (huber_px: 0.5, distortion: true, "
               "out: results); options given on the command line override it.")


def config_option(fn: Callable) -> Callable:
    """The ``--config FILE`` option (eager: read before the command's other options take their values).

    Args:
        fn: The command's function.

    Returns:
        The function with the option.
    """
    return click.option("--config", type=click.Path(path_type=Path), default=None, is_eager=True,
                        expose_value=False, callback=_apply_config, metavar="FILE", help=CONFIG_HELP)(fn)


def _apply_config(ctx: click.Context, param: click.Parameter, value: Path | None) -> None:
    """Read FILE into the command's default_map; a bad file ends the command with one error line (exit 1)."""
    if value is None:
        return
    try:
        values = read_config(value, ctx)
    except AriSfmError as exc:
        click.echo(f"error: {exc}", err=True)
        ctx.exit(1)
    ctx.default_map = {**(ctx.default_map or {}), **values}
    ctx.meta[CONFIG_META] = value


def configurable_options(command: click.Command) -> dict[str, click.Option]:
    """The options a config file may set: every visible option but --config and --help, by parameter name.

    Args:
        command: The click command.

    Returns:
        Parameter name -> its option.
    """
    return {p.name: p for p in command.params
            if isinstance(p, click.Option) and not p.hidden and p.name not in ("config", "help")}


def read_config(path: Path, ctx: click.Context) -> dict[str, Any]:
    """The file's values by parameter name, each converted by its option's type.

    Args:
        path: The YAML file.
        ctx: The command's click context (its options, its arguments, its name for the messages).

    Returns:
        Parameter name -> value, as the command line would give it (``key:`` with no value left out).

    Raises:
        AriSfmError: (path, "<key>: <what is wrong>") for an unknown key or a bad value; (path, ...) for a
            missing, empty or malformed file or one that is not a mapping.
    """
    data = as_mapping(read_structured(path), path, "")
    options = configurable_options(ctx.command)
    arguments = {p.name for p in ctx.command.params if isinstance(p, click.Argument)}
    out: dict[str, Any] = {}
    for key, value in data.items():
        name = key.replace("-", "_").lstrip("_") if isinstance(key, str) else None
        if name in arguments:
            raise AriSfmError(path, f"{key}: is an argument of `ari-sfm {ctx.command.name}`, not an option: "
                                    "give it on the command line")
        if name not in options:
            known = ", ".join(sorted(options))
            raise AriSfmError(path, f"{key if isinstance(key, str) else show(key)}: not an option of `ari-sfm "
                                    f"{ctx.command.name}` (known: {known})")
        if name in out:
            raise AriSfmError(path, f"{key}: given twice (as {name} and with dashes)")
        if value is None:  # `key:` with nothing: the option's default
            continue
        out[name] = _convert(options[name], value, ctx, path, key)
    return out


def _convert(option: click.Option, value: Any, ctx: click.Context, path: Path, key: str) -> Any:
    """``value`` as the option takes it from the command line (its type, its number of values)."""
    single = option.nargs == 1 and not option.multiple
    if not single and not isinstance(value, list):
        raise AriSfmError(path, f"{key}: must be a list of {option.nargs} values (got {show(value)})")
    is_bool = isinstance(option.type, click.types.BoolParamType)
    for item in [value] if single else value:
        if isinstance(item, (dict, list)):
            raise AriSfmError(path, f"{key}: must be {'true or false' if is_bool else 'a single value'} "
                                    f"(got {show(value)})")
        if is_bool and not isinstance(item, bool):
            raise AriSfmError(path, f"{key}: must be true or false (got {show(value)})")
        if isinstance(item, bool) and not is_bool:  # YAML's yes/no/true/false where a number or name is wanted
            raise AriSfmError(path, f"{key}: must be {_wanted(option)} (got {show(value)})")
    try:
        return option.type_cast_value(ctx, value if single else tuple(value))
    except click.BadParameter as exc:
        raise AriSfmError(path, f"{key}: {exc.message}") from None


def _wanted(option: click.Option) -> str:
    """What an option takes, in words."""
    if isinstance(option.type, click.Choice):
        return "one of " + ", ".join(map(str, option.type.choices))
    return {"float": "a number", "integer": "an integer", "path": "a path", "text": "a text"}.get(
        option.type.name, f"a {option.type.name}")


def blame_config(exc: AriSfmError) -> AriSfmError:
    """The error of a command's own check on an option's value, told against the config file when the value
    came from it.

    Args:
        exc: The error, its path the option's flag (``--huber-px``).

    Returns:
        ``error: run.yaml: huber_px: must be >= 0`` when the value came from the config file; else ``exc``
        unchanged.
    """
    ctx = click.get_current_context(silent=True)
    if ctx is None or CONFIG_META not in ctx.meta or exc.path is None:
        return exc
    for p in ctx.command.params:
        if (isinstance(p, click.Option) and exc.path in (*p.opts, *p.secondary_opts)
                and ctx.get_parameter_source(p.name) is ParameterSource.DEFAULT_MAP):
            return AriSfmError(ctx.meta[CONFIG_META], f"{p.name}: {exc.message}")
    return exc
