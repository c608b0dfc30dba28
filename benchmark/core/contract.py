"""What a depth network must be to be trained or scored here, and a user's own network.

The contract of a depth network (DepthNet and every network of kind DEPTH follow it)
-----------------------------------------------------------------------------------
- Input: ``(B, 6, H, W)`` float32, two RGB frames stacked on the channel axis (first frame,
  then second), each channel ``(x / 255 − 0.5) / 0.2`` for 8-bit values ``x``
  (core.data.normalise). DepthNet needs H and W to be multiples of 64; another network may not.
- Output: depth of the **second** frame in metres, ``(B, 1, h, w)`` with ``H / h == W / w``
  (DepthNet: h = H / 4), or a list or tuple whose first element is that map (the finest of a
  multi-scale output). The depth is the one the network would see if the camera had moved the
  *nominal displacement* between the frames; scoring multiplies it by the pair's measured
  displacement over the nominal one, then upsamples it bilinearly to H × W.

``--model module:callable`` (or ``path/to/file.py:callable``) names a function that takes no
argument and returns such a ``torch.nn.Module`` with its weights loaded: :func:`load_user_model`
builds it and checks the contract on a zero batch before any frame is scored.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path

import torch
from torch import nn

from .errors import FieldError


def depth_output(out) -> torch.Tensor:
    """The finest depth map of a network's output (a tensor, or the first of a list/tuple)."""
    return out[0] if isinstance(out, (list, tuple)) else out


def _import(spec: str):
    """The object ``module:attribute`` or ``file.py:attribute`` names."""
    module_name, sep, attribute = spec.partition(":")
    if not sep or not module_name or not attribute:
        raise FieldError("model", f"'{spec}' is not module:callable or file.py:callable")
    try:
        if module_name.endswith(".py"):
            path = Path(module_name)
            if not path.is_file():
                raise FieldError("model", f"no such file '{path}'")
            loader = importlib.util.spec_from_file_location(f"_user_model_{path.stem}", path)
            module = importlib.util.module_from_spec(loader)
            loader.loader.exec_module(module)
        else:
            if "" not in sys.path:  # the current folder, as `python -m` would search it
                sys.path.insert(0, "")
            module = importlib.import_module(module_name)
    except FieldError:
        raise
    except Exception as e:  # the user's module failed to import: say which and why
        why = f"{type(e).__name__}: {e}"
        raise FieldError("model", f"importing '{module_name}' failed: {why}") from None
    if not hasattr(module, attribute):
        raise FieldError("model", f"'{module_name}' has no '{attribute}'")
    return getattr(module, attribute)


def load_user_model(spec: str, height: int, width: int, device: torch.device) -> nn.Module:
    """The network ``spec`` builds, on ``device`` in eval mode, checked against the contract at
    the frame size ``height`` × ``width``: FieldError on ``model`` naming what is wrong."""
    build = _import(spec)
    if not callable(build):
        raise FieldError("model", f"'{spec}' is not callable")
    try:
        model = build()
    except Exception as e:
        raise FieldError("model", f"'{spec}()' failed: {type(e).__name__}: {e}") from None
    if not isinstance(model, nn.Module):
        raise FieldError("model", f"'{spec}()' returned a {type(model).__name__}, not a Module")
    check_depth_network(model.to(device).eval(), height, width, device, f"'{spec}()'")
    return model


def check_depth_network(
    model: nn.Module, height: int, width: int, device: torch.device, name: str
) -> None:
    """One forward pass of a zero ``(1, 6, height, width)`` batch: the output must be a
    ``(1, 1, h, w)`` floating-point tensor (or a list/tuple starting with one) at the frames'
    aspect ratio, finite. FieldError on ``model`` otherwise (``name``: how to call it)."""
    x = torch.zeros(1, 6, height, width, device=device)
    try:
        with torch.inference_mode():
            out = depth_output(model(x))
    except Exception as e:
        why = f"{type(e).__name__}: {e}"
        raise FieldError(
            "model", f"{name} failed on a (1, 6, {height}, {width}) input: {why}"
        ) from None
    if not isinstance(out, torch.Tensor) or not out.is_floating_point():
        raise FieldError("model", f"{name} returned {type(out).__name__}, not a float tensor")
    if out.ndim != 4 or out.shape[:2] != (1, 1) or out.shape[2] * width != out.shape[3] * height:
        raise FieldError(
            "model",
            f"{name} returned shape {tuple(out.shape)} for a (1, 6, {height}, {width}) input; "
            f"expected (1, 1, h, w) with h / w = {height} / {width} (benchmark.core.contract)",
        )
    if not torch.isfinite(out).all():
        raise FieldError("model", f"{name} returned non-finite depth for a zero input")
