"""What every group of ``stillbox-bench`` commands shares: the one-line UserError (exit code 2),
the --data and --device options and their checks, the lock of an --out folder, and small option
parsers."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import click

from stillbox_gen.conventions import default_root
from stillbox_gen.errors import ConfigError

from ..core import registry
from ..core.config import FLAGGED, KEPT_ON_RESUME, check_settings
from ..core.errors import FieldError
from ..core.registry import CLAMPED_RECIPE, DEPTH_RECIPE, UNSUPERVISED_RECIPE
from .limits import FLOAT, INT

if TYPE_CHECKING:
    import torch


class UserError(click.ClickException):
    """A user's mistake: printed as one line ``stillbox-bench: error: ...``, exit code 2."""

    exit_code = 2


#: the default --data: stillbox-gen's default output at 64 px, and the command that makes it
#: (the 3,000 scenes of docs/results/chapter-3.md)
DEFAULT_DATA = default_root(64, 64)
MAKE_DEFAULT_DATA = "stillbox-gen --res 64 --scenes 3000"


def dataset_dir(data: Path) -> Path:
    """``data`` when it holds a finished dataset or a pack of one (stillbox-gen pack; which
    one, core.data.read_dataset decides), a pack's shards all checked (size and SHA-256)
    before anything is written; else a UserError naming --data (and, when the folder is
    missing, the stillbox-gen command that makes it)."""
    if not data.exists():
        make = MAKE_DEFAULT_DATA if data == DEFAULT_DATA else f"{MAKE_DEFAULT_DATA} --out {data}"
        raise UserError(f"--data: no dataset at '{data}'; make one with '{make}'")
    from ..core.data import check_packed_shards

    try:
        check_packed_shards(data)
    except ValueError as e:
        raise UserError(f"--data: {e}") from None
    return data


@contextlib.contextmanager
def locked_out(out: Path, flag: str = "--out") -> Iterator[None]:
    """Hold the lock of the folder ``out`` (stillbox_gen.lock: ``<out>/.stillbox.lock``) for the
    block: a second command writing into the same folder is refused at once, in one line naming
    ``flag`` and the process holding it (UserError, exit code 2). ``out`` is created when
    missing and removed again at the end when the block left it empty, so a command refused
    inside the block leaves no folder behind."""
    from stillbox_gen.lock import folder_lock

    with contextlib.ExitStack() as stack:
        try:
            stack.enter_context(folder_lock(Path(out), flag))
        except ConfigError as e:  # in use, or cannot be made: errors of the block pass
            raise UserError(str(e)) from None
        yield


def torch_device(name: str) -> torch.device:
    """--device resolved to a torch.device (UserError naming --device when unusable)."""
    from ..core.device import resolve_device

    try:
        return resolve_device(name)
    except ValueError as e:
        raise user_error(e) from None


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
    return click.option(flag, type=INT, default=value, show_default=True, help=text)


DATA_OPTION = click.option(
    "--data",
    type=click.Path(path_type=Path),
    default=DEFAULT_DATA,
    show_default=True,
    help="Dataset folder made by stillbox-gen, or its pack (stillbox-gen pack) (the default "
    f"is made by '{MAKE_DEFAULT_DATA}').",
)
# ---------------------------------------------------------------- TrainConfig's settings

_FIELDS = {f.name: f for f in FLAGGED}
_TYPES = {"int": INT, "float": FLOAT, "text": str}  # numbers within limits.LIMITS


def _shown(value) -> str:
    """A recipe value as --help shows it: 0.01, 55; a range as 10,60; a word as it is."""
    if value is None or isinstance(value, str):
        return str(value)
    return ",".join(f"{v:g}" for v in value) if isinstance(value, tuple) else f"{value:g}"


#: the fields of TrainConfig whose option has no click default in ``command`` (None: the
#: default, or with --resume the run's value): finetune keeps every option of its run
KEPT_BY = {"run": KEPT_ON_RESUME, "compare": KEPT_ON_RESUME, "finetune": ("seed", *KEPT_ON_RESUME)}


def setting_option(name: str, command: str):
    """The click option of TrainConfig field ``name`` in ``command`` ("run", "compare",
    "finetune"), made from the field's Flag; its value is passed as ``name``. A recipe field
    has no click default (None: the model's recipe applies; finetune's: the unsupervised
    recipe's), nor has a field the command keeps on resume (KEPT_BY); another shows the
    field's default."""
    field_, flag = _FIELDS[name], _FIELDS[name].metadata["flag"]
    text, kw = flag.help[command], {"metavar": flag.metavar}
    if flag.kind == "flag":
        kw["is_flag"] = True
    elif flag.kind == "path":
        kw["type"] = click.Path(path_type=Path)
    elif flag.kind in _TYPES:
        kw["type"] = _TYPES[flag.kind]
    if field_.metadata["recipe"]:
        recipes = (DEPTH_RECIPE, CLAMPED_RECIPE, UNSUPERVISED_RECIPE)
        depth, clamped, unsupervised = (_shown(getattr(r, name)) for r in recipes)
        text = text.format(depth=depth, clamped=clamped, unsupervised=unsupervised)
    elif name in KEPT_BY.get(command, ()):  # None: the default, or the resumed run's value
        shown = "none" if field_.default is None else _shown(field_.default)
        resumed = "; --resume: the run's" if command in ("run", "finetune") else ""
        text += f"  [default: {shown}{resumed}]"
    elif flag.kind != "flag":
        kw.update(default=field_.default, show_default=field_.default is not None)
    return click.option(flag.decl, name, help=text, **kw)


def setting_options(command: str, order: tuple[str, ...] = ()):
    """Every click option of TrainConfig's fields that ``command`` offers: the fields in
    ``order`` first (in that order), then the others in TrainConfig's order."""
    names = [f.name for f in FLAGGED if command in f.metadata["flag"].help]
    names = [n for n in order if n in names] + [n for n in names if n not in order]

    def decorate(function):
        for name in reversed(names):  # the first option ends up first in --help
            function = setting_option(name, command)(function)
        return function

    return decorate


def flag_name(field: str) -> str:
    """The flag of a library field: a TrainConfig field's own (``depth_range``: ``--clamp``),
    else ``--`` and the field's name with dashes (``fixed_shift``: ``--fixed-shift``)."""
    if field in _FIELDS:
        return _FIELDS[field].metadata["flag"].name
    return "--" + field.replace("_", "-")


def user_error(e: ValueError, **flags: str) -> UserError:
    """A library error in the command line's terms: a FieldError names flags, not fields
    (:func:`flag_name`, or ``flags[field]`` for a command whose flag is not named after it)."""
    if not isinstance(e, FieldError):
        return UserError(str(e))
    return UserError(e.worded(lambda field: flags.get(field) or flag_name(field)))


def training_settings(o: dict) -> dict:
    """TrainConfig values from a command's setting options ``o`` (by field name; None: the
    default applies): checked against their rules and --device, then parsed. UserError
    naming the flag."""
    given = {name: value for name, value in o.items() if name in _FIELDS}
    try:
        check_settings(given)
    except FieldError as e:
        raise user_error(e) from None
    torch_device(given["device"])
    values = {}
    for name, value in given.items():
        parse = _FIELDS[name].metadata["flag"].parse
        try:
            values[name] = parse(value) if parse is not None and value is not None else value
        except ValueError as e:
            raise user_error(e) from None
    return values


DEVICE_OPTION = setting_option("device", "run")
PREDICTIONS_OPTION = setting_option("save_predictions", "run")
