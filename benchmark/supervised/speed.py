"""Size and speed of the registered networks (thesis Table 3.6).

For each network: parameters (millions), GMACs of one forward pass at several square input sizes
(models.macs: convolutions and transposed convolutions only), latency at batch 1 and throughput
at batch 8. Timing runs the network's forward pass only (eval mode, no autograd) on random
input: ``warmup`` untimed passes, then ``repeats`` timed passes, the device synchronised before
and after each; the median is reported. Depth from flow (flownets-flow) is not included: it is a
handful of element-wise operations per pixel.
"""

from __future__ import annotations

import csv
import io
import platform
import re
import statistics
import time
from pathlib import Path

import torch

from stillbox_gen.formats import atomic_write_text

from ..core import models, registry

DEFAULT_MODELS = ("depthnet", "flownets-depth", "flownets-flow")  # thesis Table 3.6's networks
DEFAULT_MAC_SIZES = (64, 128, 256, 512)  # square input sizes of the GMAC columns, pixels
DEFAULT_TIME_SIZE = 64  # square input size of the timings, pixels
DEFAULT_WARMUP = 3  # untimed passes before timing
DEFAULT_REPEATS = 20  # timed passes (the median is reported)
#: speed --train (benchmark.supervised.train_speed): DepthNet and FlowNetS (flow output, Adam),
#: batch sizes
TRAIN_MODELS = ("depthnet", "flownets-flow")
TRAIN_BATCHES = (8, 256)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@torch.inference_mode()
def time_forward(
    model: torch.nn.Module, batch: int, size: int, device: torch.device, warmup: int, repeats: int
) -> float:
    """Median seconds of one forward pass on a (batch, 6, size, size) input."""
    x = torch.randn(batch, 6, size, size, device=device)
    for _ in range(warmup):
        model(x)
    _sync(device)
    times = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        model(x)
        _sync(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def device_label(device: torch.device) -> str:
    """A file-name-safe device name: the GPU's name, or the CPU's architecture."""
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
    else:
        name = f"cpu-{platform.machine() or 'unknown'}"
    return re.sub(r"[^A-Za-z0-9.]+", "-", name).strip("-").lower()


def csv_name(device: torch.device) -> str:
    """``speed-<device>-<threads>t-torch<version>.csv``."""
    torch_version = re.sub(r"[^A-Za-z0-9.]+", "-", torch.__version__)
    return f"speed-{device_label(device)}-{torch.get_num_threads()}t-torch{torch_version}.csv"


def measure(
    names: list[str],
    device: torch.device,
    mac_sizes: tuple[int, ...] = DEFAULT_MAC_SIZES,
    time_size: int = DEFAULT_TIME_SIZE,
    batches: tuple[int, int] = (1, 8),
    warmup: int = DEFAULT_WARMUP,
    repeats: int = DEFAULT_REPEATS,
) -> list[dict]:
    """One row per network: ``params_m``, ``gmac_<s>`` per size, then at ``time_size`` px the
    batch-1 latency (``latency_ms_b1``, ``fps_b1``) and the batch-8 throughput
    (``ms_b8``, ``fps_b8``, frames per second = pairs per second)."""
    rows = []
    for name in names:
        torch.manual_seed(0)
        model = registry.build_model(name).to(device).eval()
        row: dict = {"model": name, "params_m": round(models.count_parameters(model) / 1e6, 3)}
        for s in mac_sizes:
            row[f"gmac_{s}"] = round(models.macs(model, s, s) / 1e9, 6)
        one, many = batches
        t1 = time_forward(model, one, time_size, device, warmup, repeats)
        tb = time_forward(model, many, time_size, device, warmup, repeats)
        row.update(
            {
                "time_px": time_size,
                f"latency_ms_b{one}": round(t1 * 1e3, 3),
                f"fps_b{one}": round(one / t1, 2),
                f"ms_b{many}": round(tb * 1e3, 3),
                f"fps_b{many}": round(many / tb, 2),
                "device": str(device),
                "threads": torch.get_num_threads(),
                "torch": torch.__version__,
                "warmup": warmup,
                "repeats": repeats,
            }
        )
        rows.append(row)
    return rows


def write_csv(rows: list[dict], path: Path) -> None:
    """The rows as CSV at ``path`` (folders made), written whole: under a temporary name, then
    renamed (a failed write, e.g. a full disk, is an OSError naming ``path``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    text = io.StringIO(newline="")
    w = csv.DictWriter(text, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
    atomic_write_text(path, text.getvalue())


def markdown(rows: list[dict]) -> str:
    """The rows as a markdown table (device, threads and torch columns left out)."""
    keys = [k for k in rows[0] if k not in ("device", "threads", "torch", "warmup", "repeats")]
    lines = ["| " + " | ".join(keys) + " |", "|---" * len(keys) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(str(r[k]) for k in keys) + " |")
    return "\n".join(lines)
