"""A trained depth network that leaves the project: ONNX, TorchScript or safetensors.

The exported network (``onnx``, ``torchscript``) has one input and one output:

- input ``frames``: ``(B, 6, H, W)`` float32, two RGB frames stacked on the channel axis (the
  earlier frame first), each channel ``(x / 255 - 0.5) / 0.2`` for 8-bit values ``x``; H × W is
  the training camera's size (fixed in the file), B is free.
- output ``depth``: ``(B, 1, H, W)`` float32, metres, the depth of the **second** frame as if the
  camera had moved the nominal displacement ``d0`` between the two: multiply by ``d / d0`` for a
  pair whose camera moved ``d`` metres. It is the network's finest output upsampled bilinearly
  to H × W (as ``eval`` scores it), clamped to the training range for a clamped network.

``safetensors`` holds the bare weights, to be loaded into ``registry.build_model(model_name)``.
Every format records :func:`metadata` (input size, normalisation, ``d0``, depth range, camera)
as JSON under :data:`METADATA_KEY`: ONNX ``metadata_props``, a TorchScript extra file
``stillbox.json``, the safetensors header's metadata.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch
from torch import nn

from stillbox_gen.arguments import unwritable
from stillbox_gen.formats import temp_path

from ..core.checkpoint import first_line, source_error
from ..core.contract import depth_output
from ..core.data import NORM_MEAN, NORM_STD
from ..core.errors import FieldError
from ..core.metrics import upsample_to
from ..core.multishift import DepthScale
from .network import depth_network

FORMATS = {"onnx": ".onnx", "torchscript": ".pt", "safetensors": ".safetensors"}
#: where each format keeps the JSON of :func:`metadata`
METADATA_KEY = "stillbox"
#: version of the metadata's layout
METADATA_VERSION = 1
#: ONNX operator set of the exported graph
OPSET = 18


class DeployedDepth(nn.Module):
    """One depth network as exported: normalised frame pair in, full-size depth (m) out."""

    def __init__(self, network: nn.Module, clamp: tuple[float, float] | None):
        super().__init__()
        self.network, self.clamp = network, clamp

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        depth = depth_output(self.network(frames))
        if self.clamp is not None:
            depth = depth.clamp(*self.clamp)
        return upsample_to(depth, frames.shape[-2], frames.shape[-1]).unsqueeze(1)


def metadata(info: dict, scale: DepthScale) -> dict:
    """What a user of the exported file needs (JSON-able): sizes in pixels, distances in metres,
    the field of view in horizontal degrees."""
    return {
        "version": METADATA_VERSION,
        "model_name": info["model_name"],
        "input": {
            "name": "frames",
            "shape": ["B", 6, info["height"], info["width"]],
            "layout": "RGB of the earlier frame, then RGB of the later frame",
            "normalisation": f"(x / 255 - {NORM_MEAN}) / {NORM_STD} for 8-bit x",
        },
        "output": {
            "name": "depth",
            "shape": ["B", 1, info["height"], info["width"]],
            "unit": "m",
            "meaning": "depth of the later frame at the nominal displacement; "
            "multiply by d / nominal_displacement_m for a camera that moved d metres",
        },
        "nominal_displacement_m": scale.d0,
        "depth_range_m": list(info["depth_range"]),
        "camera": {k: info[k] for k in ("width", "height", "fov_deg")},
    }


def _write(out: Path, write) -> None:
    """``write(tmp)`` then rename to ``out``: a failed export leaves nothing behind."""
    tmp = temp_path(out)
    try:
        write(tmp)
        os.replace(tmp, out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def check_out(out: Path, fmt: str) -> None:
    """FieldError on ``out`` unless it is a new file with the format's suffix in a folder."""
    if out.suffix != FORMATS[fmt]:
        raise FieldError("out", f"'{out}' must end in {FORMATS[fmt]} for --format {fmt}")
    if out.exists() or out.is_symlink():
        raise FieldError("out", f"'{out}' exists; give a new file (nothing is overwritten)")
    if not out.parent.is_dir():
        raise FieldError("out", f"no such folder '{out.parent}'")
    if problem := unwritable(out.parent):  # e.g. /proc, whose permissions say root may write
        raise FieldError("out", problem)


def export(ckpt: Path, fmt: str, out: Path) -> dict:
    """Write the depth network of checkpoint ``ckpt`` to ``out`` in format ``fmt``; return its
    metadata. ValueError of one line (naming ``ckpt`` or ``out``) for an unusable input."""
    check_out(out, fmt)
    network, scale, info = depth_network(ckpt, "ckpt")
    meta = metadata(info, scale)
    text = json.dumps(meta)
    if fmt == "safetensors":
        from safetensors.torch import save_file

        weights = {k: v.contiguous() for k, v in network.state_dict().items()}
        _write(out, lambda tmp: save_file(weights, str(tmp), metadata={METADATA_KEY: text}))
        return meta
    model = DeployedDepth(network, info["clamp"]).eval()
    example = torch.zeros(1, 6, info["height"], info["width"])
    if fmt == "torchscript":
        with torch.no_grad():
            traced = torch.jit.trace(model, example)
        extra = {f"{METADATA_KEY}.json": text}
        _write(out, lambda tmp: torch.jit.save(traced, str(tmp), _extra_files=extra))
        return meta
    _write(out, lambda tmp: _export_onnx(model, example, tmp, text))
    return meta


def _export_onnx(model: nn.Module, example: torch.Tensor, path: Path, text: str) -> None:
    import onnx

    batch = torch.export.Dim("batch", min=1, max=1024)
    program = torch.onnx.export(
        model,
        (example,),
        input_names=["frames"],
        output_names=["depth"],
        dynamic_shapes={"frames": {0: batch}},
        opset_version=OPSET,
        dynamo=True,
        verbose=False,
    )
    proto = program.model_proto
    entry = proto.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, text
    onnx.save(proto, str(path))


class OnnxDepthNetwork:
    """An exported ONNX depth network behind the call of a torch network: ``net(frames)``
    returns ``(depth,)`` as torch tensors on the CPU (onnxruntime's CPU provider)."""

    def __init__(self, path: Path, field: str | None = "ckpt"):
        try:
            import onnxruntime
        except ImportError:
            raise source_error(
                field, path, "needs onnxruntime to run: pip install 'stillbox-gen[export]'"
            ) from None

        options = onnxruntime.SessionOptions()
        options.log_severity_level = 3  # errors only: no optimiser chatter on stderr
        try:
            self.session = onnxruntime.InferenceSession(
                str(path), options, providers=["CPUExecutionProvider"]
            )
        except Exception as e:  # noqa: BLE001 - any loader failure is the file's fault
            raise source_error(field, path, f"not a runnable ONNX file ({first_line(e)})") from None

    def __call__(self, frames: torch.Tensor) -> tuple[torch.Tensor]:
        x = np.ascontiguousarray(frames.detach().cpu().numpy(), dtype=np.float32)
        (depth,) = self.session.run(["depth"], {"frames": x})
        return (torch.from_numpy(depth),)

    def to(self, device: torch.device) -> OnnxDepthNetwork:
        if torch.device(device).type != "cpu":
            raise ValueError("an ONNX network runs on the CPU here; give --device cpu")
        return self

    def eval(self) -> OnnxDepthNetwork:
        return self


def read_onnx_metadata(path: Path, field: str | None = "ckpt") -> dict:
    """The :func:`metadata` of an ONNX file written by :func:`export`."""
    try:
        import onnx
    except ImportError:
        raise source_error(
            field, path, "needs onnx to read: pip install 'stillbox-gen[export]'"
        ) from None
    try:
        proto = onnx.load(str(path), load_external_data=False)
    except Exception:  # noqa: BLE001 - any reader failure is the file's fault
        raise source_error(field, path, "not a readable ONNX file") from None
    props = {p.key: p.value for p in proto.metadata_props}
    try:
        meta = json.loads(props[METADATA_KEY])
        meta["camera"]["width"], meta["nominal_displacement_m"]  # noqa: B018 - presence check
    except (KeyError, TypeError, ValueError):
        raise source_error(
            field, path, "an ONNX file without stillbox metadata (export it with "
            "'stillbox-bench export')"
        ) from None  # fmt: skip
    return meta


def onnx_depth_network(
    path: Path, field: str | None = "ckpt", camera: dict | None = None
) -> tuple[OnnxDepthNetwork, DepthScale, dict]:
    """``(model, scale, info)`` of an exported ONNX file, as :func:`network.depth_network`
    returns them for a checkpoint (``camera`` overrides the recorded training camera)."""
    from ..core.registry import output_clamp

    meta = read_onnx_metadata(path, field)
    lo, hi = (float(v) for v in meta["depth_range_m"])
    info = dict(camera if camera is not None else meta["camera"])
    info.update(depth_range=[lo, hi], clamp=output_clamp((lo, hi)), model_name=meta["model_name"])
    scale = DepthScale(theta_max=hi, d0=float(meta["nominal_displacement_m"]))
    return OnnxDepthNetwork(path, field), scale, info
