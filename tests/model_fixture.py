"""Describe every registered network as ``tests/fixtures/models.json`` records it.

The fixture was generated from the networks *before* DepthNet and FlowNetS shared their
encoder-decoder code (``python tests/model_fixture.py`` at that commit), and guards that refactor
and any later one: the same state_dict names, shapes and order (checkpoints of earlier runs and of
the public DepthNet/FlowNetS code load with ``strict=True``; an optimiser state keeps its
parameter order) and, for one seed, the same initial weights and outputs.

Per network:

- ``state_dict``: ``{name: shape}`` in state_dict order (parameters and buffers);
- ``parameters``: parameter names in ``named_parameters`` order (an optimiser's state order);
- ``init_sha256``: SHA-256 of the float32 bytes of every state_dict tensor after
  ``torch.manual_seed(0)`` and building the network;
- ``outputs``: the network loaded (``strict=True``) with :func:`synthetic_state_dict`, a
  state_dict built from the recorded names and shapes alone, run on an input of
  :data:`INPUT_SHAPE` drawn from ``torch.Generator().manual_seed(1)``, in eval and in train mode
  (BatchNorm on batch statistics): per output scale ``[sum, sum of |x|]`` (float64) and the
  SHA-256 of all outputs' float32 bytes. (Loaded weights rather than the initial ones, whose
  flow head is zero: every layer of every network shapes these numbers.)

Exact checksums depend on the CPU kernels: ``init_sha256`` is compared only under the torch
version and ATen CPU capability recorded in ``environment``; the outputs' checksums are kept as
recorded but not compared (oneDNN also picks kernels by instruction set, AMX and thread count),
their sums are, within the tolerance of tests/test_models.py.

``python tests/model_fixture.py`` rewrites the fixture; ``--describe NAME...`` prints the records
of those networks as JSON (for runs under other kernel settings).
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import torch

from benchmark.core import registry

FIXTURE = Path(__file__).parent / "fixtures" / "models.json"
INPUT_SHAPE = (2, 6, 64, 128)


def environment() -> dict:
    """What exact float32 results depend on: torch's version and the CPU kernels it picks."""
    return {"torch": torch.__version__, "cpu_capability": torch.backends.cpu.get_cpu_capability()}


def sha256(tensors) -> str:
    h = hashlib.sha256()
    for t in tensors:
        h.update(t.detach().to(torch.float32).contiguous().numpy().tobytes())
    return h.hexdigest()


def synthetic_state_dict(shapes: dict[str, list[int]]) -> dict[str, torch.Tensor]:
    """A state_dict of the given ``{name: shape}`` with values from a seeded generator:
    weights ~ N(0, 1 / (numel / shape[0])), BatchNorm weights near 1, running variances in
    [0.5, 1.5), ``num_batches_tracked`` 0: what a checkpoint of these names would hold."""
    g = torch.Generator().manual_seed(2)
    state = {}
    for name, shape in shapes.items():
        if name.endswith("num_batches_tracked"):
            state[name] = torch.tensor(0)
        elif name.endswith("running_var"):
            state[name] = torch.rand(shape, generator=g) + 0.5
        elif len(shape) == 1:  # biases, BN weights and means
            offset = 1.0 if name.endswith("weight") else 0.0
            state[name] = offset + 0.1 * torch.randn(shape, generator=g)
        else:
            fan = max(1, torch.Size(shape).numel() // shape[0])
            state[name] = torch.randn(shape, generator=g) / fan**0.5
    return state


def outputs(model: torch.nn.Module, train: bool) -> dict:
    x = torch.randn(*INPUT_SHAPE, generator=torch.Generator().manual_seed(1))
    model.train(train)
    with torch.no_grad():
        outs = model(x)
    sums = [[o.double().sum().item(), o.double().abs().sum().item()] for o in outs]
    return {"sums": sums, "sha256": sha256(outs)}


def describe(name: str) -> dict:
    """The record of registered network ``name`` (see the module doc)."""
    torch.manual_seed(0)
    model = registry.build_model(name)
    state = model.state_dict()
    shapes = {k: list(v.shape) for k, v in state.items()}
    init = sha256(state.values())
    model.load_state_dict(synthetic_state_dict(shapes), strict=True)
    return {
        "state_dict": shapes,
        "parameters": [k for k, _ in model.named_parameters()],
        "init_sha256": init,
        "outputs": {"eval": outputs(model, False), "train": outputs(model, True)},
    }


def trainable() -> list[str]:
    return [n for n in registry.list_models() if registry.MODELS[n].trainable]


def load() -> dict:
    """The recorded fixture."""
    return json.loads(FIXTURE.read_text())


def main() -> None:
    record = {"environment": environment(), "models": {n: describe(n) for n in trainable()}}
    FIXTURE.parent.mkdir(exist_ok=True)
    text = json.dumps(record, indent=1)
    text = re.sub(r"\[\s*([^\[\]{}\"]*?)\s*\]", lambda m: f"[{' '.join(m[1].split())}]", text)
    FIXTURE.write_text(text + "\n")
    print(f"wrote {FIXTURE}")


if __name__ == "__main__":
    import sys

    if sys.argv[1:2] == ["--describe"]:
        print(json.dumps({n: describe(n) for n in sys.argv[2:]}))
    else:
        main()
