"""The finished runs of an unfinished toy study, kept so that ``stillbox-bench toy --resume``
goes on from the last finished run (the full study is 13 batched runs of up to ~2.7 h in all).

Layout, inside the study's ``--out`` folder::

    toy-runs/study.json          the study's settings (:func:`settings`), written at its start
    toy-runs/<key>.npz           one finished run: its results.json block and its BestRun

``<key>`` is the run's key in results.json (``photometric`` or ``<loss>/odm-<off|on>``) with the
"/" as "."; one ``.npz`` per run, written atomically (a temporary name, then a rename) as the run
ends, holds everything (JSON texts as 0-d string arrays; no pickle, read with
``allow_pickle=False``): ``block`` (the results.json block), ``study`` (the settings it was run
with), ``label``, ``scenes``, ``history_iterations`` and per scene ``depth/<scene>`` (1, 1, H, W)
metres, ``history/<scene>`` (T,) LE, ``occluded/<scene>/<i>`` (1, 1, H, W) bool per reference
(ODM runs only). Everything is read back exactly (float32 as float32, JSON floats by their repr),
so a resumed study writes the same results as an uninterrupted one but for the timings.
The folder is removed once the study's outputs are written (:func:`remove`).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import torch

from stillbox_gen.formats import TEMP_INFIX, atomic_write, atomic_write_text

from .toy import BestRun, StudyConfig, ToyScene

FOLDER = "toy-runs"
STUDY_JSON = "study.json"
#: Settings that choose which runs a study holds, not what a run computes: a study resumed with
#: other losses or ODM settings takes the finished runs it asks for, so halves of a study run
#: in parallel (one process per core, ``--losses`` split) combine by copying their run files
SELECTION = ("losses", "odm")


def folder(out: Path) -> Path:
    return Path(out) / FOLDER


def run_path(out: Path, key: str) -> Path:
    """``toy-runs/<key>.npz`` of results.json's run ``key``."""
    return folder(out) / f"{key.replace('/', '.')}.npz"


def scene_digest(scene: ToyScene) -> str:
    """SHA-256 (hex) of what a toy scene gives the study: its frames, true depth, valid mask,
    K and poses, as loaded (float32 / bool bytes)."""
    h = hashlib.sha256(scene.name.encode())
    tensors = [scene.frames, scene.depth, scene.valid, scene.K]
    tensors += [x for pose in scene.poses for x in pose]
    for t in tensors:
        a = np.ascontiguousarray(t.detach().cpu().numpy())
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def settings(cfg: StudyConfig, scenes: list[ToyScene]) -> dict:
    """What a resumed study must share with the interrupted one (JSON types): iterations, grids,
    ODM period and settings, losses, and each scene's data (:func:`scene_digest`)."""
    return {
        "iterations": cfg.iterations,
        "lambdas": list(cfg.lambdas),
        "kappas": list(cfg.kappas),
        "odm_every": cfg.odm_every,
        "odm": list(cfg.odm),
        "losses": list(cfg.losses),
        "scenes": {s.name: scene_digest(s) for s in scenes},
    }


def read_settings(out: Path) -> dict | None:
    """``toy-runs/study.json``, or None when there is none; an unreadable one is a one-line
    ValueError naming it."""
    path = folder(out) / STUDY_JSON
    if not path.is_file():
        return None
    try:
        saved = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"'{path}' is not a readable toy study ({e}); remove it") from None
    if not isinstance(saved, dict):
        raise ValueError(f"'{path}' is not a toy study's settings; remove it")
    return saved


def shared(study: dict) -> dict:
    """``study``'s settings but :data:`SELECTION`: what every run of the study shares."""
    return {k: v for k, v in study.items() if k not in SELECTION}


def difference(saved: dict, requested: dict) -> str | None:
    """The first setting where ``saved`` differs from ``requested`` in words, by the flag of
    ``stillbox-bench toy`` that sets it ("--iterations 20, now 30"; "other --flower data"), or
    None when they match (:data:`SELECTION` aside)."""
    for key, value in shared(requested).items():
        was = saved.get(key)
        if was == value:
            continue
        if key == "scenes" and isinstance(was, dict):
            names = [n for n in value if was.get(n) != value[n]] or list(value)
            return f"other {', '.join('--' + n for n in names)} data"
        return f"--{key.replace('_', '-')} {was}, now {value}"
    return None


def finished(out: Path) -> list[str]:
    """Keys of the runs saved in ``toy-runs/``."""
    if not folder(out).is_dir():
        return []
    return sorted(p.stem.replace(".", "/") for p in folder(out).glob("*.npz"))


def start(out: Path, study: dict) -> None:
    """A new study: ``toy-runs/`` emptied of an earlier study's files, then its settings."""
    remove(out)
    folder(out).mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder(out) / STUDY_JSON, json.dumps(study, indent=2) + "\n")


def remove(out: Path) -> None:
    """Delete ``toy-runs/``: study.json and the run files (nothing else is touched; the folder
    is removed when that leaves it empty)."""
    d = folder(out)
    if not d.is_dir():
        return
    (d / STUDY_JSON).unlink(missing_ok=True)
    for p in [*d.glob("*.npz"), *d.glob(f".*{TEMP_INFIX}*")]:  # and a killed writer's temp file
        p.unlink()
    if not any(d.iterdir()):
        d.rmdir()


def _text(value: str) -> np.ndarray:
    return np.array(value, dtype=np.str_)


def save(out: Path, key: str, block: dict, best: BestRun, study: dict) -> None:
    """Write run ``key``'s results.json ``block`` and ``best`` (one file, atomically)."""
    arrays = {
        "block": _text(json.dumps(block)),
        "study": _text(json.dumps(study)),
        "label": _text(best.label),
        "scenes": np.array(list(best.depth), dtype=np.str_),
        "history_iterations": np.array(best.history_iterations, dtype=np.int64),
    }
    for name, depth in best.depth.items():
        arrays[f"depth/{name}"] = depth.numpy()
        arrays[f"history/{name}"] = np.asarray(best.history[name])
        for i, mask in enumerate(best.occluded[name] or []):
            arrays[f"occluded/{name}/{i}"] = mask.numpy()
    atomic_write(run_path(out, key), lambda f: np.savez(f, **arrays))


def load(out: Path, key: str, study: dict) -> tuple[dict, BestRun]:
    """Run ``key`` as :func:`save` wrote it: ``(block, BestRun)``. A file that cannot be read,
    or that was run with other settings than ``study``, is a one-line ValueError naming it."""
    path = run_path(out, key)
    try:
        with np.load(path, allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        if shared(json.loads(str(a["study"]))) != shared(study):
            raise ValueError("run with other settings than study.json")
        names = [str(n) for n in a["scenes"]]
        occluded: dict[str, list[torch.Tensor] | None] = {}
        for n in names:
            masks = []
            while f"occluded/{n}/{len(masks)}" in a:
                masks.append(torch.from_numpy(a[f"occluded/{n}/{len(masks)}"]))
            occluded[n] = masks or None
        best = BestRun(
            label=str(a["label"]),
            depth={n: torch.from_numpy(a[f"depth/{n}"]) for n in names},
            occluded=occluded,
            history={n: a[f"history/{n}"] for n in names},
            history_iterations=a["history_iterations"].tolist(),
        )
        return json.loads(str(a["block"])), best
    except Exception as e:  # noqa: BLE001 - any reader failure (zip, header, key, JSON) is the file's
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise ValueError(f"'{path}' is not a readable toy run ({msg}); remove it") from None
