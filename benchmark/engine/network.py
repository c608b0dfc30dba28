"""A trained depth network ready for inference on frames: the checkpoint's network, how its
output becomes metres (:class:`benchmark.core.multishift.DepthScale`) and its training camera."""

from __future__ import annotations

from pathlib import Path

import torch

from stillbox_gen.conventions import MAX_DEPTH

from ..core import registry
from ..core.checkpoint import load_checkpoint, load_weights, source_error
from ..core.data import DataError, camera_of
from ..core.errors import Ref
from ..core.multishift import DepthScale


def _training_camera(ck: dict, field: str | None, path: str | Path) -> dict:
    """The training camera ``{"width", "height", "fov_deg"}`` (pixels, pixels, horizontal
    degrees): the checkpoint's ``camera`` entry, else its training dataset's (data.camera_of)."""
    cam = ck.get("camera")
    if not isinstance(cam, dict):
        data = (ck.get("config") or {}).get("data")
        try:
            return camera_of(str(data))
        except (DataError, KeyError, TypeError):
            raise source_error(
                field, path,
                f"no training camera (the checkpoint has none and its dataset '{data}' is not "
                "readable); give ", Ref("train_fov"), " DEG and ", Ref("res"), " WxH",
            ) from None  # fmt: skip
    return {"width": cam["width"], "height": cam["height"], "fov_deg": float(cam["fov_deg"])}


def depth_network(
    path: str | Path, field: str | None = "ckpt", camera: dict | None = None
) -> tuple[torch.nn.Module, DepthScale, dict]:
    """A depth network ready for inference: ``(model, scale, info)``.

    ``model``: the checkpoint's network in eval mode on the CPU; ``scale``:
    :class:`benchmark.core.multishift.DepthScale` with ``theta_max`` = the upper bound of the
    training depth range (m; MAX_DEPTH unless the checkpoint has a ``depth_range``) and ``d0`` = its
    nominal displacement (m); ``info``: the training camera (``width``, ``height`` in pixels,
    ``fov_deg`` horizontal degrees; from the checkpoint's ``camera``, else from its training
    dataset's dataset.json, else ``camera`` given here, which also overrides them),
    ``depth_range`` [lo, hi] (m), ``clamp`` (the range outputs must be clamped to, None unless
    narrower than [0, MAX_DEPTH]: registry.output_clamp) and ``model_name``. A checkpoint of a
    method that does not output depth (flow networks) is refused: ValueError of one line naming
    the file and the ``field`` it was given as (checkpoint.source_error).
    """
    ck = load_checkpoint(path, field)
    name = ck["model_name"]
    kind = registry.MODELS[name].kind
    if kind.scored_as is not registry.Scoring.DEPTH:
        raise source_error(
            field,
            path,
            f"'{name}' predicts {kind.name}, not depth; give a depth network's checkpoint",
        )
    model = registry.build_model(name)
    load_weights(model, ck, field, path, name)
    model.eval()
    lo, hi = (float(v) for v in ck.get("depth_range", (0.0, MAX_DEPTH)))  # load_checkpoint
    d0 = float(ck["nominal_displacement"])  # checked them (check_metadata)
    info = camera if camera is not None else _training_camera(ck, field, path)
    info = {**info, "depth_range": [lo, hi], "clamp": registry.output_clamp((lo, hi))}
    return model, DepthScale(theta_max=hi, d0=d0), {**info, "model_name": name}
