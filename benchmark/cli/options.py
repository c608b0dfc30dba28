"""What every group of ``stillbox-bench`` commands shares: the one-line UserError (exit code 2),
the --data and --device options and their checks, and small option parsers."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import click

from stillbox_gen.conventions import default_root

from ..core import registry
from ..core.config import default

if TYPE_CHECKING:
    import torch


class UserError(click.ClickException):
    """A user's mistake: printed as one line ``stillbox-bench: error: ...``, exit code 2."""

    exit_code = 2


#: the default --data: stillbox-gen's default output at 64 px, and the command that makes it
#: (the 3,000 scenes of the README's results)
DEFAULT_DATA = default_root(64, 64)
MAKE_DEFAULT_DATA = "stillbox-gen --res 64 --scenes 3000"


def dataset_dir(data: Path) -> Path:
    """``data`` when it holds a finished dataset; else a UserError naming --data (and, when the
    folder is missing, the stillbox-gen command that makes it)."""
    if not data.exists():
        make = MAKE_DEFAULT_DATA if data == DEFAULT_DATA else f"{MAKE_DEFAULT_DATA} --out {data}"
        raise UserError(f"--data: no dataset at '{data}'; make one with '{make}'")
    if not (data / "manifest.parquet").is_file():
        raise UserError(
            f"--data: '{data}' is not a finished stillbox-gen dataset (no manifest.parquet)"
        )
    return data


def torch_device(name: str) -> torch.device:
    """--device resolved to a torch.device (UserError naming --device when unusable)."""
    from ..core.device import resolve_device

    try:
        return resolve_device(name)
    except ValueError as e:
        raise UserError(str(e)) from None


def is_default(name: str) -> bool:
    """True when the current command's option ``name`` was not given (its default applies)."""
    source = click.get_current_context().get_parameter_source(name)
    return source is click.core.ParameterSource.DEFAULT


def model_names(value: str) -> list[str]:
    """--models "a,b" -> registered names (UserError naming --models for unknown or none)."""
    names = [n.strip() for n in value.split(",") if n.strip()]
    unknown = [n for n in names if n not in registry.MODELS]
    if not names or unknown:
        raise UserError(
            f"--models: unknown {', '.join(map(repr, unknown)) or 'empty list'} "
            f"(registered: {', '.join(registry.list_models())})"
        )
    return names


def int_option(flag: str, value: int, text: str):
    """An integer option with a default shown in --help."""
    return click.option(flag, type=int, default=value, show_default=True, help=text)


DATA_OPTION = click.option(
    "--data",
    type=click.Path(path_type=Path),
    default=DEFAULT_DATA,
    show_default=True,
    help=f"Dataset folder made by stillbox-gen (the default is made by '{MAKE_DEFAULT_DATA}').",
)
DEVICE_OPTION = click.option(
    "--device", default=default("device"), show_default=True, help="auto | cpu | cuda | cuda:N."
)
PREDICTIONS_OPTION = click.option(
    "--save-predictions",
    is_flag=True,
    help="Store predicted depth maps (float32 .npy, full resolution).",
)
