"""``stillbox-bench export``: a depth network as an ONNX, TorchScript or safetensors file."""

from __future__ import annotations

import importlib.util
import json
import logging
import warnings
from pathlib import Path

import click

from stillbox_gen.layout import enclosing_dataset

from .options import UserError, user_error

#: the packages each format needs beyond the `bench` extra (the `export` extra has them)
NEEDS = {"onnx": ("onnx", "onnxscript"), "safetensors": ("safetensors",), "torchscript": ()}


@click.command("export")
@click.option(
    "--ckpt", type=click.Path(path_type=Path), required=True, help="Depth checkpoint of 'run'."
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["onnx", "torchscript", "safetensors"]),
    default="onnx",
    show_default=True,
    help="onnx / torchscript: frames in, full-size depth (m) out; safetensors: the weights.",
)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    required=True,
    help="New file: .onnx, .pt (torchscript) or .safetensors.",
)
def export_cmd(ckpt: Path, fmt: str, out: Path) -> None:
    """Write a depth network for use outside the project (docs/RUNS.md, "Exporting").

    The file records the input size, the normalisation, the nominal displacement and the depth
    range; `infer --ckpt model.onnx` runs an exported ONNX file.
    """
    from ..engine.export import export

    missing = [m for m in NEEDS[fmt] if importlib.util.find_spec(m) is None]
    if missing:
        raise UserError(
            f"--format {fmt} needs {', '.join(missing)}: pip install 'stillbox-gen[export]'"
        )
    inside = enclosing_dataset(out.parent) if out.parent.exists() else None
    if inside is not None:
        raise UserError(f"--out: '{out}' is inside the dataset '{inside}'; write elsewhere")
    try:
        with warnings.catch_warnings(), _quiet("torch.onnx", "torch.export", "torch._dynamo"):
            warnings.simplefilter("ignore")  # tracer and exporter notes, not the user's concern
            meta = export(ckpt, fmt, out)
    except ValueError as e:
        raise user_error(e) from None
    click.echo(f"wrote {out} ({fmt}, {out.stat().st_size / 1e6:.1f} MB)")
    click.echo(json.dumps(meta, indent=1))


class _quiet:
    """Raise the named loggers to ERROR for the duration of a ``with`` block."""

    def __init__(self, *names: str):
        self.loggers = [logging.getLogger(n) for n in names]

    def __enter__(self) -> None:
        self.levels = [lg.level for lg in self.loggers]
        for lg in self.loggers:
            lg.setLevel(logging.ERROR)

    def __exit__(self, *exc) -> None:
        for lg, level in zip(self.loggers, self.levels, strict=True):
            lg.setLevel(level)
