"""Options made from a settings class: one per field, named after it (`--kebab-name`, less the
command's prefix), with the field's description as help and its default shown, so that a setting
is described and defaulted in one place. An option left out is None, so the environment, the TOML
file and the default apply in that order (see `load_settings`). `fleet serve` makes its options
from the depot's `Settings`, `fleet agent` from `AgentSettings`."""

from __future__ import annotations

import enum
import types
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Union, get_args, get_origin

import click

if TYPE_CHECKING:
    from pydantic.fields import FieldInfo

    from services.settings import SharedSettings


class SettingsCommand(click.Command):
    """A command whose options are made from its settings class when first needed (help, parsing):
    importing it (pydantic-settings) would otherwise slow every other `fleet` command."""

    # The settings class, imported when first needed.
    settings_class: Callable[[], type[SharedSettings]]
    # Dropped from field names in the flags (the agent's `agent_spool` is `--spool`).
    flag_prefix: ClassVar[str] = ""
    # Settings that are no option, and why (shown after the options).
    not_options: ClassVar[dict[str, str]] = {}
    # Options also read from a variable of the CLI's own (as every command that talks to the depot).
    envvars: ClassVar[dict[str, str]] = {}

    _made = False

    def get_params(self, ctx: click.Context) -> list[click.Parameter]:
        if not self._made:
            self.params[:0] = self.settings_options()
            self._made = True
        return super().get_params(ctx)

    def settings_options(self) -> list[click.Option]:
        """One option per field of the settings class but `not_options`: the command's own first,
        then those both programs share (pydantic lists a base class's fields first)."""
        from services.settings import SharedSettings

        settings = self.settings_class()
        prefix = str(settings.model_config.get("env_prefix", ""))
        fields = sorted(settings.model_fields.items(), key=lambda item: item[0] in SharedSettings.model_fields)
        return [self._option(name, field, prefix) for name, field in fields if name not in self.not_options]

    def _option(self, name: str, field: FieldInfo, env_prefix: str) -> click.Option:
        flag = "--" + name.removeprefix(self.flag_prefix).replace("_", "-")
        envvar = self.envvars.get(name)
        variables = " or ".join(v for v in (f"{env_prefix}{name.upper()}", envvar) if v)
        kind = _without_none(field.annotation)
        repeatable = " (repeatable)" if get_origin(kind) is list else ""
        help_text = f"{variables}: {field.description}{repeatable}{_shown_default(field)}"
        if kind is bool:
            return click.Option([f"{flag}/--no-{flag[2:]}", name], default=None, help=help_text)
        if get_origin(kind) is list:  # repeatable, and each value may itself be a comma-separated or JSON list
            return click.Option(
                [flag, name],
                type=_click_type(name, kind),
                multiple=True,
                default=None,
                callback=_list_value,
                help=help_text,
                envvar=envvar,
            )
        return click.Option([flag, name], type=_click_type(name, kind), default=None, help=help_text, envvar=envvar)

    def format_epilog(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        settings = self.settings_class()
        prefix = str(settings.model_config.get("env_prefix", ""))
        fields = settings.model_fields
        with formatter.section("Settings without an option"):
            formatter.write_dl(
                [
                    (f"{prefix}{name.upper()}", f"{fields[name].description} ({why})")
                    for name, why in self.not_options.items()
                ]
            )
        super().format_epilog(ctx, formatter)


def _list_value(ctx: click.Context, param: click.Parameter, value: tuple[str, ...] | None) -> Any:
    """None when the flag is left out (the environment, the TOML file or the default apply); one
    value as given (the setting reads a comma-separated or JSON list); several as the list."""
    if not value:
        return None
    return value[0] if len(value) == 1 else list(value)


def _without_none(annotation: Any) -> Any:
    """`X` for `X | None`."""
    if get_origin(annotation) in (Union, types.UnionType):
        (annotation,) = [arg for arg in get_args(annotation) if arg is not type(None)]
    return annotation


def _click_type(name: str, kind: Any) -> click.ParamType[Any] | type:
    if kind is Path:
        return click.Path(path_type=Path)
    if isinstance(kind, type) and issubclass(kind, enum.Enum):
        return click.Choice([member.value for member in kind])
    from pydantic import SecretStr

    if kind is SecretStr:
        return str
    if kind in (str, int, float):
        return kind  # type: ignore[no-any-return]
    if get_origin(kind) is list and get_args(kind) in ((str,), (SecretStr,), (Path,)):
        return str  # the field's validator reads a comma-separated or JSON list
    raise TypeError(f"setting {name} ({kind}) has no option type: add one, or name it in the command's not_options")


def _shown_default(field: FieldInfo) -> str:
    value = field.get_default(call_default_factory=True)
    if value in ("", None):
        return ""  # the description says what an unset value means
    if isinstance(value, bool):
        value = "on" if value else "off"
    elif isinstance(value, list):
        value = ", ".join(map(str, value))  # also a value the option takes
    elif isinstance(value, enum.Enum):
        value = value.value
    return f" [default: {value}]"
